//! The session's event channel: publishing, and raw subscriptions (lossy when they fall behind:
//! streams read through [`super::EventStream`], which re-synchronises instead).

use std::sync::Arc;

use tokio::sync::broadcast;

use super::Session;
use crate::api::wire::SessionEvent;
use crate::api::ServiceError;

impl Session {
    /// A raw receiver: falling more than the channel's capacity behind skips events silently
    /// (`RecvError::Lagged`). Clients' streams use [`Self::stream`].
    pub fn subscribe(&self) -> broadcast::Receiver<Arc<SessionEvent>> {
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
        // No subscribers is fine.
        let _ = self.events.send(event);
    }

    /// Event-stream subscribers now (the zenoh publisher included).
    pub fn subscribers(&self) -> usize {
        self.events.receiver_count()
    }
}
