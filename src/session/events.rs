//! The session's event stream: subscribing (within `limits.max_subscribers`) and publishing.

use std::sync::Arc;

use tokio::sync::broadcast;

use super::Session;
use crate::api::wire::SessionEvent;
use crate::api::ErrorKind;
use crate::api::ServiceError;

impl Session {
    pub fn subscribe(&self) -> broadcast::Receiver<Arc<SessionEvent>> {
        self.events.subscribe()
    }

    /// Publishes a rejection of something sent to this session without a reply channel (a
    /// zenoh put), so subscribers of its stream see it.
    pub fn report_rejection(&self, error: ServiceError) {
        crate::runtime::metrics::count_rejection(&error.body);
        self.emit(SessionEvent::Error {
            session: self.name.clone(),
            sequence: None,
            error: error.body,
        });
    }

    pub(super) fn emit(&self, event: SessionEvent) {
        // No subscribers is fine.
        let _ = self.events.send(Arc::new(event));
    }

    /// Event-stream subscribers now (the zenoh publisher included).
    pub fn subscribers(&self) -> usize {
        self.events.receiver_count()
    }

    /// A new event-stream subscriber, or 429 at `limits.max_subscribers`.
    pub fn subscribe_limited(
        &self,
    ) -> Result<broadcast::Receiver<Arc<SessionEvent>>, ServiceError> {
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
        Ok(self.subscribe())
    }
}
