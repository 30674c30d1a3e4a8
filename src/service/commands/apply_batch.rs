//! `apply_batch`: validated whole, applied whole or not at all, journalled before it is
//! acknowledged; with `wait`, answered once the estimate reflects it.

use crate::api::{Accepted, ApplyBatch, ServiceError};
use crate::runtime::metrics;
use crate::service::{durability, Caller, Service};

impl Service {
    pub(super) async fn apply_batch(
        &self,
        caller: &Caller,
        request: ApplyBatch,
    ) -> Result<Accepted, ServiceError> {
        let ApplyBatch {
            session,
            batch,
            wait,
        } = request;
        let session = self.writable_as(caller, &session)?;
        let (ack, will_solve) = if session.waits_for_fsync() {
            durability::apply_waiting_for_fsync(&session, batch).await?
        } else {
            session.apply_batch(batch)?
        };
        metrics::count_accepted_batch();
        let solved = if wait && will_solve {
            // With a latency budget, a provisional answer ends the wait too.
            let done = session
                .wait_answered(ack.sequence, self.wait_timeout())
                .await;
            Some(done && session.last_error().is_none())
        } else if wait {
            Some(session.solved_sequence() >= ack.sequence)
        } else {
            None
        };
        let exact_sequence = solved
            .and(session.max_update_ms())
            .map(|_| session.solved_sequence());
        Ok(Accepted {
            exact: exact_sequence.map(|exact| exact >= ack.sequence),
            exact_sequence,
            ack,
            solved,
        })
    }
}
