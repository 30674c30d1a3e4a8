//! What a session remembers of its stream for the web view: every event it publishes passes
//! through [`History::record`], which keeps a bounded timeline of solves and the last events of
//! the log (see `api::history`). A durable session writes it to its directory when it changed
//! ([`StoredHistory`], written by `durable/history_file.rs`) and reads it back when it is
//! rebuilt, so the timeline and the log outlive a restart or a move to another instance.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use super::{Origin, Session};
use crate::api::history::{
    LoggedData, LoggedEvent, SessionHistory, TimelinePoint, LOGGED_EVENTS, REJECTIONS,
    TIMELINE_POINTS,
};
use crate::api::wire::SessionEvent;
use crate::api::ServiceError;

#[derive(Default)]
pub(super) struct History {
    timeline: VecDeque<TimelinePoint>,
    events: VecDeque<LoggedEvent>,
    rejected: VecDeque<LoggedEvent>,
    /// When each batch not yet reflected by a solve was accepted, by sequence (oldest first).
    accepted: VecDeque<(u64, Instant)>,
    dropped: u64,
    /// What `events` and `rejected` hold, kept as they change (see [`History::bytes`]).
    logged_bytes: usize,
    /// Counts the changes (recorded events), and the count the history file was written at.
    revision: u64,
    written: u64,
}

/// The history as a session's directory keeps it (`history.json`): what `GET …/history` shows
/// but `last_error`, which the session's own state holds. `format` is 1. Written from the
/// logged events themselves (shared, serialised as streamed), read back as [`StoredEvent`]s.
#[derive(serde::Serialize, serde::Deserialize)]
pub(super) struct StoredHistory<E> {
    pub format: u32,
    pub timeline: Vec<TimelinePoint>,
    pub events: Vec<E>,
    pub rejected: Vec<E>,
    pub dropped: u64,
}

/// A logged event as read back: its stream's name and the event as it was streamed (the
/// fields a [`LoggedEvent`] serialises to).
#[derive(serde::Deserialize)]
pub(super) struct StoredEvent {
    pub unix_ms: u64,
    pub event: String,
    pub data: serde_json::Value,
}

pub(super) const STORED_HISTORY_FORMAT: u32 = 1;

impl StoredEvent {
    /// Back as a logged event; `None` for a stream the log does not keep.
    fn restored(self) -> Option<LoggedEvent> {
        let event = ["acks", "summary", "errors"]
            .into_iter()
            .find(|name| *name == self.event)?;
        let bytes = serde_json::to_string(&self.data).map_or(0, |s| s.len());
        Some(LoggedEvent {
            unix_ms: self.unix_ms,
            event,
            data: LoggedData::Restored {
                event: Arc::new(self.data),
                bytes,
            },
        })
    }
}

fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// Pushes `item`, dropping the oldest beyond `cap`; counts what was dropped and returns it.
fn push_bounded<T>(queue: &mut VecDeque<T>, item: T, cap: usize, dropped: &mut u64) -> Option<T> {
    queue.push_back(item);
    if queue.len() <= cap {
        return None;
    }
    *dropped += 1;
    queue.pop_front()
}

/// [`push_bounded`] for the event log and the rejections, keeping their byte count.
fn push_logged(
    queue: &mut VecDeque<LoggedEvent>,
    item: LoggedEvent,
    cap: usize,
    dropped: &mut u64,
    bytes: &mut usize,
) {
    *bytes += logged_bytes(&item);
    if let Some(old) = push_bounded(queue, item, cap, dropped) {
        *bytes -= logged_bytes(&old);
    }
}

/// One logged event with its heap parts (an ack's ids, an error's text). An event the
/// stream's buffer still shares is counted here too, as the history outlives it.
fn logged_bytes(e: &LoggedEvent) -> usize {
    use std::mem::size_of;
    let event = match &e.data {
        LoggedData::Live(event) => event,
        LoggedData::Restored { bytes, .. } => return size_of::<LoggedEvent>() + bytes,
    };
    size_of::<LoggedEvent>()
        + size_of::<SessionEvent>()
        + match event.as_ref() {
            SessionEvent::Ack(ack) => {
                ack.factor_ids.len() * size_of::<crate::api::wire::FactorId>()
                    + ack.predicted.len() * size_of::<crate::variables::Key>()
                    + ack.session.len()
            }
            SessionEvent::Error { session, error, .. } => {
                session.len() + error.message.len() + error.field.as_ref().map_or(0, String::len)
            }
            _ => 0,
        }
}

impl History {
    /// What the history holds, for `memory_bytes`: O(1), from the logged events' byte count
    /// kept as they come and go and the fixed-size entries of the other queues.
    pub(super) fn bytes(&self) -> usize {
        use std::mem::size_of;
        self.timeline.len() * size_of::<TimelinePoint>()
            + self.accepted.len() * size_of::<(u64, Instant)>()
            + self.logged_bytes
    }

    /// The history to write out, when it changed since it was last written: the stored form
    /// and the revision it is at (for [`History::written_at`]). Built from the events' shared
    /// data; the caller serialises it after releasing the history's lock.
    pub(super) fn changed_since_written(&self) -> Option<(u64, StoredHistory<LoggedEvent>)> {
        (self.revision != self.written).then(|| {
            let stored = StoredHistory {
                format: STORED_HISTORY_FORMAT,
                timeline: self.timeline.iter().cloned().collect(),
                events: self.events.iter().cloned().collect(),
                rejected: self.rejected.iter().cloned().collect(),
                dropped: self.dropped,
            };
            (self.revision, stored)
        })
    }

    /// The history file now holds the history as of `revision`.
    pub(super) fn written_at(&mut self, revision: u64) {
        self.written = self.written.max(revision);
    }

    /// The history a session's directory kept, before anything of this process is recorded
    /// (bounded as a live one; events of streams the log does not keep are left out).
    pub(super) fn restored(stored: StoredHistory<StoredEvent>) -> Self {
        let mut history = Self {
            dropped: stored.dropped,
            ..Self::default()
        };
        let mut ignored = 0;
        for point in stored.timeline {
            push_bounded(&mut history.timeline, point, TIMELINE_POINTS, &mut ignored);
        }
        for (stored, queue, cap) in [
            (stored.events, &mut history.events, LOGGED_EVENTS),
            (stored.rejected, &mut history.rejected, REJECTIONS),
        ] {
            for event in stored.into_iter().filter_map(StoredEvent::restored) {
                push_logged(queue, event, cap, &mut ignored, &mut history.logged_bytes);
            }
        }
        history
    }

    pub(super) fn record(&mut self, event: &Arc<SessionEvent>) {
        self.revision += 1;
        let now = unix_ms();
        let logged = || LoggedEvent {
            unix_ms: now,
            event: event.topic(),
            data: LoggedData::Live(event.clone()),
        };
        match event.as_ref() {
            SessionEvent::Ack(ack) => {
                if !ack.reflected {
                    // Bounded like the timeline: a session that never solves keeps the newest.
                    let mut ignored = 0;
                    push_bounded(
                        &mut self.accepted,
                        (ack.sequence, Instant::now()),
                        TIMELINE_POINTS,
                        &mut ignored,
                    );
                }
                self.log(logged());
            }
            SessionEvent::Summary {
                solve,
                sequence,
                summary,
                ..
            } => {
                let point = self.solve_point(now, *solve, *sequence, summary);
                self.plot(point);
                self.log(logged());
            }
            SessionEvent::State {
                iterations,
                update_seconds,
                ..
            } => self.plot(TimelinePoint {
                unix_ms: now,
                solve: 0,
                sequence: 0,
                chi2: None,
                solve_seconds: *update_seconds,
                latency_seconds: Some(*update_seconds),
                iterations: *iterations,
                converged: true,
            }),
            // Merges and outlier decisions are rare and worth keeping in the log the web view
            // shows.
            SessionEvent::Merge { .. } | SessionEvent::Outliers { .. } => self.log(logged()),
            SessionEvent::Error { .. } => {
                self.log(logged());
                push_logged(
                    &mut self.rejected,
                    logged(),
                    REJECTIONS,
                    &mut self.dropped,
                    &mut self.logged_bytes,
                );
            }
            SessionEvent::Iteration { .. }
            | SessionEvent::Estimate(_)
            | SessionEvent::Window { .. }
            | SessionEvent::Lagged { .. } => {}
        }
    }

    /// The timeline point of a finished solve reflecting `sequence`; its latency runs from
    /// the oldest batch it is the first to reflect.
    fn solve_point(
        &mut self,
        now: u64,
        solve: u64,
        sequence: u64,
        summary: &crate::solver::Summary,
    ) -> TimelinePoint {
        let mut oldest = None;
        while let Some(&(seq, at)) = self.accepted.front() {
            if seq > sequence {
                break;
            }
            oldest.get_or_insert(at);
            self.accepted.pop_front();
        }
        TimelinePoint {
            unix_ms: now,
            solve,
            sequence,
            chi2: Some(summary.final_chi2).filter(|c| c.is_finite()),
            solve_seconds: summary.solve_seconds,
            latency_seconds: oldest.map(|at| at.elapsed().as_secs_f64()),
            iterations: summary.iterations,
            converged: summary.converged,
        }
    }

    fn plot(&mut self, point: TimelinePoint) {
        push_bounded(
            &mut self.timeline,
            point,
            TIMELINE_POINTS,
            &mut self.dropped,
        );
    }

    fn log(&mut self, event: LoggedEvent) {
        push_logged(
            &mut self.events,
            event,
            LOGGED_EVENTS,
            &mut self.dropped,
            &mut self.logged_bytes,
        );
    }
}

impl Session {
    /// Keeps a refusal answered to its sender (an rpc) in the history's rejected inputs, as
    /// streamed refusals are, without publishing it: `origin` names the batch's producer.
    pub fn note_rejection(&self, error: &ServiceError, origin: Option<Origin>) {
        let event = Arc::new(self.rejection_event(error.body.clone(), origin));
        let mut history = self.history.lock().unwrap_or_else(|p| p.into_inner());
        history.record(&event);
    }

    /// The session's timeline, recent events and rejections (see `api::history`).
    pub fn history(&self) -> SessionHistory {
        let last_error = self.last_error();
        let h = self.history.lock().unwrap_or_else(|p| p.into_inner());
        SessionHistory {
            session: self.name.clone(),
            timeline: h.timeline.iter().cloned().collect(),
            events: h.events.iter().cloned().collect(),
            rejected: h.rejected.iter().cloned().collect(),
            last_error,
            dropped: h.dropped,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::api::wire::BatchAck;

    fn ack(sequence: u64, factors: usize) -> Arc<SessionEvent> {
        Arc::new(SessionEvent::Ack(BatchAck {
            session: "s".into(),
            sequence,
            factor_ids: (0..factors as u64).collect(),
            predicted: Vec::new(),
            reflected: true,
            producer: None,
            producer_seq: None,
            accepted_through: None,
            duplicate: false,
        }))
    }

    #[test]
    fn its_bytes_count_what_logged_acks_carry_and_stay_bounded() {
        let mut history = History::default();
        history.record(&ack(1, 0));
        let small = history.bytes();
        history.record(&ack(2, 1000));
        assert!(history.bytes() >= small + 8000, "{}", history.bytes());
        for sequence in 3..10 * LOGGED_EVENTS as u64 {
            history.record(&ack(sequence, 1000));
        }
        // The log keeps the last LOGGED_EVENTS: its bytes stop growing.
        let full = history.bytes();
        assert!(
            (LOGGED_EVENTS * 8000..LOGGED_EVENTS * 9000).contains(&full),
            "{full}"
        );
    }
}
