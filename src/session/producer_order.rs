//! Ordering across transports: a request that says "after my batches" (`after_producer`,
//! `after_seq`) waits until the session has applied that producer's batches up to that number,
//! whichever transport each travelled on (a zenoh put and an rpc query are not ordered with
//! each other), and where each producer stands.

use std::collections::BTreeMap;
use std::time::Duration;

use super::Session;
use crate::api::wire::ProducerStatus;
use crate::api::ServiceError;

/// Where the session stands: what a `lagged` marker carries.
#[derive(Clone, Debug, PartialEq)]
pub struct Progress {
    /// The latest accepted sequence.
    pub sequence: u64,
    /// The sequence the estimate reflects.
    pub reflected_sequence: u64,
    /// Every producer's `accepted_through`.
    pub producers: BTreeMap<String, u64>,
}

impl Session {
    pub fn progress(&self) -> Progress {
        let st = self.lock();
        Progress {
            sequence: st.mirror.sequence,
            reflected_sequence: st.results.solved_sequence,
            producers: st.producers.progress(),
        }
    }

    pub fn producer_status(&self, producer: &str) -> ProducerStatus {
        let st = self.lock();
        ProducerStatus {
            session: self.name.clone(),
            producer: producer.to_string(),
            accepted_through: st.producers.accepted_through(producer),
            sequence: st.producers.last_sequence(producer),
            reflected_sequence: st.results.solved_sequence,
        }
    }

    /// Waits until `producer`'s batches up to `seq` are applied, at most `timeout`: 503
    /// `after_timeout` (Retry-After 1) naming how far it got; 404 if the session is deleted
    /// meanwhile.
    pub async fn wait_after(
        &self,
        producer: &str,
        seq: u64,
        timeout: Duration,
    ) -> Result<(), ServiceError> {
        let mut accepted = self.accepted.subscribe();
        let reached = |session: &Session| {
            let st = session.lock();
            if st.schedule.phase.is_deleted() {
                return Err(session.gone());
            }
            Ok(st.producers.accepted_through(producer))
        };
        let deadline = tokio::time::Instant::now() + timeout;
        loop {
            // Marked seen before the check, so an acceptance after it wakes the wait below.
            accepted.borrow_and_update();
            let through = reached(self)?;
            if through >= seq {
                return Ok(());
            }
            let changed = tokio::time::timeout_at(deadline, accepted.changed()).await;
            if !matches!(changed, Ok(Ok(()))) {
                let through = reached(self)?;
                if through >= seq {
                    return Ok(());
                }
                return Err(ServiceError::unavailable(
                    "after_timeout",
                    format!(
                        "session `{}` has applied batches 1 to {through} of producer \
                         `{producer}`, not yet {seq}, after {} ms: the rest is still on its \
                         way or was lost (resend it)",
                        self.name,
                        timeout.as_millis()
                    ),
                    1,
                )
                .at("after_seq"));
            }
        }
    }
}
