//! `optimize`: solve now whatever the policy (after the producer's batches it names); with
//! `wait`, answered with the statistics once the solve is over.

use crate::api::{Optimize, Optimizing, ServiceError};
use crate::service::{Caller, Service};

impl Service {
    pub(super) async fn optimize(
        &self,
        caller: &Caller,
        request: Optimize,
    ) -> Result<Optimizing, ServiceError> {
        let session = self.writable_as(caller, &request.session)?;
        super::wait_after(&session, request.after.resolve()?).await?;
        let (sequence, solve) = session.optimize_now()?;
        let stats = if request.wait {
            session.wait_solve(solve, self.wait_timeout()).await;
            Some(Box::new(session.stats()))
        } else {
            None
        };
        Ok(Optimizing {
            session: session.name.clone(),
            sequence,
            stats,
        })
    }
}
