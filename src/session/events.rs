//! The session's event channel: publishing, and raw subscriptions (lossy when they fall behind:
//! streams read through [`super::EventStream`], which re-synchronises instead).
//!
//! The channel carries weak references: what keeps a published event alive is
//! [`RetainedEvents`], the newest ones up to `limits.max_subscriber_lag` of them and
//! `limits.max_subscriber_lag_bytes` together. A subscriber that falls further behind finds the event
//! gone and re-synchronises, as when it falls more events behind than the channel holds. The
//! channel alone kept its last 4096 events, whatever their size: a session with a latency
//! budget at 250 000 poses publishes corrections of most of its map, megabytes each, and the
//! 300 000-pose stream was killed for memory at 23 GB with a 1.7 GB session.

use std::collections::VecDeque;
use std::sync::{Arc, Weak};

use tokio::sync::broadcast;

use super::Session;
use crate::api::wire::SessionEvent;
use crate::api::ServiceError;

impl Session {
    /// A raw receiver: falling more than the channel's capacity behind skips events silently
    /// (`RecvError::Lagged`), and an event no longer retained upgrades to `None`. Clients'
    /// streams use [`Self::stream`].
    pub fn subscribe(&self) -> broadcast::Receiver<Weak<SessionEvent>> {
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
        let weak = Arc::downgrade(&event);
        self.retained
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .keep(event);
        // No subscribers is fine.
        let _ = self.events.send(weak);
    }

    /// What the retained events hold (for `memory_bytes`).
    pub(super) fn retained_event_bytes(&self) -> usize {
        self.retained
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .bytes
    }

    /// Event-stream subscribers now (the zenoh publisher included).
    pub fn subscribers(&self) -> usize {
        self.events.receiver_count()
    }
}

/// The newest published events, at most `capacity` of them and `max_bytes` (the newest is
/// kept whatever its size).
pub(super) struct RetainedEvents {
    events: VecDeque<(Arc<SessionEvent>, usize)>,
    capacity: usize,
    max_bytes: usize,
    bytes: usize,
}

impl RetainedEvents {
    pub fn new(capacity: usize, max_bytes: usize) -> Self {
        Self {
            events: VecDeque::new(),
            capacity,
            max_bytes,
            bytes: 0,
        }
    }

    fn keep(&mut self, event: Arc<SessionEvent>) {
        let size = approximate_bytes(&event);
        self.events.push_back((event, size));
        self.bytes += size;
        while self.events.len() > 1
            && (self.events.len() > self.capacity || self.bytes > self.max_bytes)
        {
            if let Some((_, size)) = self.events.pop_front() {
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
    fn events_are_retained_up_to_their_count_and_bytes_and_the_newest_always() {
        const MAX_BYTES: usize = 1 << 20;
        let mut retained = RetainedEvents::new(4, MAX_BYTES);
        let small: Vec<_> = (0..6).map(|_| estimate(1)).collect();
        for event in &small {
            retained.keep(Arc::clone(event));
        }
        let weak: Vec<_> = small.iter().map(Arc::downgrade).collect();
        drop(small);
        let alive = weak.iter().filter(|w| w.upgrade().is_some()).count();
        assert_eq!(alive, 4, "the newest four");
        // One event larger than the byte bound: kept alone, everything older dropped.
        let big = estimate(MAX_BYTES / 40);
        assert!(approximate_bytes(&big) > MAX_BYTES);
        let big_weak = Arc::downgrade(&big);
        retained.keep(big);
        assert!(big_weak.upgrade().is_some());
        assert!(weak.iter().all(|w| w.upgrade().is_none()));
        assert_eq!(retained.events.len(), 1);
        // Freed as soon as a newer one pushes it past the bound.
        retained.keep(estimate(1));
        assert!(big_weak.upgrade().is_none());
        assert!(retained.bytes < 1024, "{}", retained.bytes);
    }
}
