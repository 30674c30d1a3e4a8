//! A subscriber of the session's events that cannot lose silently: every stream (zenoh
//! publications, SSE, WebSocket) reads through [`EventStream`], so they share one semantics.
//!
//! The session publishes into one bounded broadcast channel. A subscriber that falls more than
//! its capacity behind loses the oldest events. Instead of skipping them silently, the stream
//! then yields a re-synchronisation:
//! 1. a [`SessionEvent::Lagged`] marker: how many events were skipped, the session's latest
//!    accepted and reflected sequences, and every producer's `accepted_through` (cumulative
//!    acknowledgements: no acknowledgement is lost with it);
//! 2. one [`SessionEvent::Estimate`] holding the current value of every variable whose value
//!    may have changed in what was skipped (latest-value semantics: the latest is never lost).
//!
//! After a lag the subscriber continues from the live end of the channel: the events still
//! queued for it are dropped too (the re-synchronisation covers their acknowledgements and
//! values; a subscriber left at the far end of a full channel would only lag again). Skipped
//! iteration statistics, summaries and errors are not repeated: the marker's `skipped` says how
//! many events were lost.
//!
//! Which variables: a mirror entry's `changed` is the sequence of the batch or of the solve
//! that set it. Batches take increasing sequences, and solves run one at a time, each with the
//! session sequence at its start, so the sequences of the estimate events of each kind never
//! decrease. Every value set after the last event this subscriber saw therefore has `changed` at
//! least the smaller of the highest acknowledged sequence it saw (its batch estimate follows the
//! acknowledgement) and the sequence of the last solve it saw finish; the re-synchronisation
//! sends every entry from there. That may repeat values it had: harmless with latest-value
//! semantics. (A solve's sequence is also at least the reflected sequence when it starts, which
//! nothing but its own end raises meanwhile: at subscription and after a re-synchronisation the
//! marks are the session's sequence and reflected sequence.)

use std::collections::VecDeque;
use std::sync::{Arc, Weak};

use tokio::sync::broadcast::{self, error::RecvError, error::TryRecvError};

use super::engine::Engine;
use super::Session;
use crate::api::wire::{Estimate, SessionEvent};
use crate::api::ErrorKind;
use crate::api::ServiceError;

/// One subscriber of a session's events; see the module documentation.
pub struct EventStream {
    /// Weak: a subscriber must not keep a deleted session alive (its channel closes with it).
    session: Weak<Session>,
    receiver: broadcast::Receiver<Arc<super::events::EventSlot>>,
    /// The highest acknowledged sequence seen (at subscription: the session's sequence).
    acked: u64,
    /// The sequence of the last solve seen finish (at subscription: the reflected sequence).
    solved: u64,
    /// What a re-synchronisation still has to yield (its estimate).
    queued: VecDeque<Arc<SessionEvent>>,
}

impl Session {
    /// A subscriber of this session's events that re-synchronises instead of skipping.
    pub fn stream(self: &Arc<Self>) -> EventStream {
        // Under the lock: events are published under it, so the marks below match exactly what
        // the receiver will see.
        let st = self.lock();
        EventStream {
            session: Arc::downgrade(self),
            receiver: self.events.subscribe(),
            acked: st.mirror.sequence,
            solved: st.results.solved_sequence,
            queued: VecDeque::new(),
        }
    }

    /// [`Self::stream`] within `limits.max_subscribers`: 429 `too_many_subscribers` beyond it.
    pub fn stream_limited(self: &Arc<Self>) -> Result<EventStream, ServiceError> {
        if self.subscribers() >= self.limits.max_subscribers {
            let mut e = ServiceError::new(
                ErrorKind::TooMany,
                "too_many_subscribers",
                format!(
                    "session `{}` has {} event subscribers, the limit (limits.max_subscribers)",
                    self.name, self.limits.max_subscribers
                ),
            )
            .at("session");
            e.body.retry_after = Some(5);
            return Err(e);
        }
        Ok(self.stream())
    }

    /// The topics this session's events are published under (every `SessionEvent::topic` it
    /// emits): where a publisher per topic puts a `lagged` marker.
    pub fn topics(&self) -> &'static [&'static str] {
        match self.engine {
            // Only a session with robots merges; any graph session may hold possibly wrong
            // closures.
            Engine::Graph(_) if self.lock().robots.is_some() => &[
                "acks", "poses", "stats", "summary", "errors", "outliers", "merges",
            ],
            Engine::Graph(_) => &["acks", "poses", "stats", "summary", "errors", "outliers"],
            Engine::Window(_) => &["state", "window", "errors"],
        }
    }

    /// The lagged marker, the estimate of every variable changed from sequence `from` on (if
    /// any), and the (sequence, reflected sequence) the marker names.
    fn resynchronisation(
        &self,
        skipped: u64,
        from: u64,
    ) -> (SessionEvent, Option<SessionEvent>, (u64, u64)) {
        let progress = self.progress();
        let marks = (progress.sequence, progress.reflected_sequence);
        let marker = SessionEvent::Lagged {
            session: self.name.clone(),
            skipped,
            sequence: progress.sequence,
            reflected_sequence: progress.reflected_sequence,
            producers: progress.producers,
        };
        let st = self.lock();
        let variables: Vec<_> = st
            .mirror
            .entries
            .iter()
            .filter(|(_, e)| e.changed >= from)
            .map(|(&k, e)| super::mirror::value_of(k, e))
            .collect();
        let estimate = (!variables.is_empty()).then(|| {
            SessionEvent::Estimate(Estimate {
                session: self.name.clone(),
                sequence: st.mirror.sequence,
                variables,
            })
        });
        (marker, estimate, marks)
    }
}

impl EventStream {
    /// The next event; `None` once the session is gone. After a lag: the marker, then the
    /// estimate of what changed meanwhile, then the events published from the lag on.
    pub async fn next(&mut self) -> Option<Arc<SessionEvent>> {
        if let Some(event) = self.queued.pop_front() {
            return Some(event);
        }
        match self.receiver.recv().await {
            Ok(event) => self.received(&event),
            Err(RecvError::Lagged(skipped)) => self.lagged(skipped),
            Err(RecvError::Closed) => None,
        }
    }

    /// The next event if one is ready now (as [`Self::next`]), else `None` (also when the
    /// session is gone: [`Self::next`] tells).
    pub fn try_next(&mut self) -> Option<Arc<SessionEvent>> {
        if let Some(event) = self.queued.pop_front() {
            return Some(event);
        }
        match self.receiver.try_recv() {
            Ok(event) => self.received(&event),
            Err(TryRecvError::Lagged(skipped)) => self.lagged(skipped),
            Err(TryRecvError::Empty | TryRecvError::Closed) => None,
        }
    }

    /// An event from the channel; one the session took back (this subscriber fell further
    /// behind than the session keeps events for) is a lag of one.
    fn received(&mut self, slot: &super::events::EventSlot) -> Option<Arc<SessionEvent>> {
        match slot.event() {
            Some(event) => Some(self.seen(event)),
            None => self.lagged(1),
        }
    }

    fn seen(&mut self, event: Arc<SessionEvent>) -> Arc<SessionEvent> {
        match &*event {
            SessionEvent::Ack(ack) => self.acked = self.acked.max(ack.sequence),
            SessionEvent::Summary { sequence, .. } => self.solved = self.solved.max(*sequence),
            _ => {}
        }
        event
    }

    fn lagged(&mut self, skipped: u64) -> Option<Arc<SessionEvent>> {
        let session = self.session.upgrade()?;
        // Jump to the live end first (nothing published from here on is missed), dropping
        // what is still queued: the re-synchronisation covers it too, and a subscriber left
        // at the far end of a full channel would only lag again.
        let queued = self.receiver.len() as u64;
        self.receiver = self.receiver.resubscribe();
        let from = self.acked.min(self.solved);
        let (marker, estimate, (sequence, reflected)) =
            session.resynchronisation(skipped + queued, from);
        // Everything changed before the re-synchronisation is in it; what changes later has a
        // sequence after `sequence`, or is a solve's, at least `reflected`.
        (self.acked, self.solved) = (sequence, reflected);
        if let Some(estimate) = estimate {
            self.queued.push_back(Arc::new(estimate));
        }
        Some(Arc::new(marker))
    }
}
