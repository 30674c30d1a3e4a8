//! The session's event channel: publishing, and raw subscriptions (lossy when they fall behind:
//! streams read through [`super::EventStream`], which re-synchronises instead).
//!
//! The channel carries [`EventSlot`]s. A slot holds its event until every subscriber has taken
//! it (the channel then drops it) or until the session takes it back: the events some subscriber
//! has not taken yet may hold at most `limits.max_subscriber_lag_bytes` together
//! ([`UnreadEvents`]; the newest is kept whatever its size). A subscriber that finds an event
//! taken back re-synchronises, as one that fell more events behind than the channel holds. The
//! channel alone bounded only their count (4 096): one slow subscriber of a large map, whose
//! corrections are megabytes each, could make the session hold gigabytes.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex, Weak};

use tokio::sync::broadcast;

use super::Session;
use crate::api::wire::SessionEvent;
use crate::api::ServiceError;

impl Session {
    /// A raw receiver: falling more than the channel's capacity behind skips events silently
    /// (`RecvError::Lagged`), and a slot whose event the session took back is empty. Clients'
    /// streams use [`Self::stream`].
    pub fn subscribe(&self) -> broadcast::Receiver<Arc<EventSlot>> {
        self.events.subscribe()
    }

    /// Publishes a rejection of something sent to this session without a reply channel (a
    /// zenoh put), so subscribers of its stream see it; `origin`: the rejected batch's producer
    /// fields, so its producer can tell which batch it was.
    pub fn report_rejection(&self, error: ServiceError, origin: Option<super::Origin>) {
        crate::runtime::metrics::count_rejection(&error.body);
        self.emit(self.rejection_event(error.body, origin));
    }

    /// The `error` event of a refused input, naming its producer's numbering when it had one.
    pub(super) fn rejection_event(
        &self,
        error: crate::api::ErrorBody,
        origin: Option<super::Origin>,
    ) -> SessionEvent {
        let (producer, producer_seq) = origin.map(|o| (o.producer, o.seq)).unzip();
        SessionEvent::Error {
            session: self.name.clone(),
            sequence: None,
            error,
            producer,
            producer_seq,
        }
    }

    pub(super) fn emit(&self, event: SessionEvent) {
        let event = Arc::new(event);
        self.history
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .record(&event);
        let size = approximate_bytes(&event);
        let slot = Arc::new(EventSlot(Mutex::new(Some(event))));
        // No subscribers is fine: the slot is dropped at once.
        let _ = self.events.send(Arc::clone(&slot));
        self.unread
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .track(&slot, size);
    }

    /// What the events not yet taken by every subscriber hold (for `memory_bytes`).
    pub(super) fn unread_event_bytes(&self) -> usize {
        self.unread.lock().unwrap_or_else(|p| p.into_inner()).bytes
    }

    /// Event-stream subscribers now (the zenoh publisher included).
    pub fn subscribers(&self) -> usize {
        self.events.receiver_count()
    }
}

/// A published event as the channel carries it (see the module documentation).
#[derive(Debug)]
pub struct EventSlot(Mutex<Option<Arc<SessionEvent>>>);

impl EventSlot {
    /// The event, unless the session took it back.
    pub fn event(&self) -> Option<Arc<SessionEvent>> {
        self.0.lock().unwrap_or_else(|p| p.into_inner()).clone()
    }

    fn take_back(&self) {
        self.0.lock().unwrap_or_else(|p| p.into_inner()).take();
    }
}

/// The published events some subscriber has not taken yet, oldest first, with their sizes: at
/// most `max_bytes` together (the newest is kept whatever its size).
pub(super) struct UnreadEvents {
    slots: VecDeque<(Weak<EventSlot>, usize)>,
    max_bytes: usize,
    bytes: usize,
}

impl UnreadEvents {
    pub fn new(max_bytes: usize) -> Self {
        Self {
            slots: VecDeque::new(),
            max_bytes,
            bytes: 0,
        }
    }

    fn track(&mut self, slot: &Arc<EventSlot>, size: usize) {
        self.slots.push_back((Arc::downgrade(slot), size));
        self.bytes += size;
        // Slots every subscriber has taken are gone (the channel dropped them).
        while let Some((oldest, size)) = self.slots.front() {
            if oldest.strong_count() > 0 {
                break;
            }
            self.bytes -= size;
            self.slots.pop_front();
        }
        if self.bytes <= self.max_bytes {
            return;
        }
        self.slots.retain(|(slot, _)| slot.strong_count() > 0);
        self.bytes = self.slots.iter().map(|(_, size)| size).sum();
        while self.bytes > self.max_bytes && self.slots.len() > 1 {
            if let Some((oldest, size)) = self.slots.pop_front() {
                if let Some(slot) = oldest.upgrade() {
                    slot.take_back();
                }
                self.bytes -= size;
            }
        }
    }
}

/// About what an event holds: its lists' elements by their size (the values of an estimate's
/// variables are inline), the rest as the enum's own size.
fn approximate_bytes(event: &SessionEvent) -> usize {
    use std::mem::size_of;
    let lists = match event {
        SessionEvent::Estimate(estimate) => {
            estimate.variables.len() * (size_of::<crate::api::wire::VariableValue>() + 8)
        }
        SessionEvent::Summary { summary, .. } => {
            summary.iteration_log.len() * size_of::<crate::solver::IterationReport>()
        }
        SessionEvent::Window {
            keyframes,
            smoothed,
            ..
        } => (keyframes.len() + smoothed.len()) * size_of::<crate::api::fusion::StateReport>(),
        SessionEvent::Outliers { decisions, .. } => {
            (decisions.accepted.len() + decisions.rejected.len())
                * size_of::<crate::api::outliers::CandidateReport>()
        }
        _ => 0,
    };
    size_of::<SessionEvent>() + lists
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::api::wire::{Estimate, VariableValue};

    fn estimate(variables: usize) -> Arc<SessionEvent> {
        let value = VariableValue {
            key: 0,
            kind: "se2".into(),
            value: vec![0.0; 3].into(),
            changed: 1,
            stamp: None,
        };
        Arc::new(SessionEvent::Estimate(Estimate {
            session: "s".into(),
            sequence: 1,
            variables: vec![value; variables],
        }))
    }

    #[test]
    fn unread_events_are_bounded_by_bytes_and_taken_ones_cost_nothing() {
        const MAX_BYTES: usize = 1 << 20;
        let mut unread = UnreadEvents::new(MAX_BYTES);
        let slot = |variables| Arc::new(EventSlot(Mutex::new(Some(estimate(variables)))));
        // Slots no subscriber holds any more (taken by all) are forgotten.
        for _ in 0..10 {
            let taken = slot(1);
            unread.track(&taken, approximate_bytes(&taken.event().unwrap()));
        }
        assert_eq!(unread.slots.len(), 1, "only the newest is still counted");
        // Slots still held (not taken by some subscriber) count, up to the bound.
        let held: Vec<_> = (0..4).map(|_| slot(1)).collect();
        for s in &held {
            unread.track(s, approximate_bytes(&s.event().unwrap()));
        }
        assert!(held.iter().all(|s| s.event().is_some()));
        // One larger than the bound: kept alone, the older unread ones taken back.
        let big = slot(MAX_BYTES / 40);
        let size = approximate_bytes(&big.event().unwrap());
        assert!(size > MAX_BYTES);
        unread.track(&big, size);
        assert!(big.event().is_some(), "the newest is kept");
        assert!(
            held.iter().all(|s| s.event().is_none()),
            "the older ones taken back"
        );
        // Taken back as soon as a newer one pushes it past the bound.
        let next = slot(1);
        unread.track(&next, approximate_bytes(&next.event().unwrap()));
        assert!(big.event().is_none());
        assert!(unread.bytes < 1024, "{}", unread.bytes);
    }
}
