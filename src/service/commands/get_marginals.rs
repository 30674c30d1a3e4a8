//! `get_marginals`: marginal covariances of `keys` at the current estimate (and their joint
//! covariance), computed off the async threads, and asked again after a running solve (which
//! holds the problem) finishes.

use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::api::wire::{Marginals, MarginalsQuery};
use crate::api::{GetMarginals, ServiceError};
use crate::service::{off_async, Caller, Service};
use crate::session::Session;

impl Service {
    pub(super) async fn get_marginals(
        &self,
        caller: &Caller,
        request: GetMarginals,
    ) -> Result<Box<Marginals>, ServiceError> {
        let session = self.writable_as(caller, &request.session)?;
        let query = MarginalsQuery {
            keys: request.keys,
            joint: request.joint,
        };
        self.marginals(session, query).await.map(Box::new)
    }

    /// Marginals off the async threads; while a solve holds the problem, asks again after it
    /// (polling: a queued solve may find nothing to do and finish without a trace).
    async fn marginals(
        &self,
        session: Arc<Session>,
        query: MarginalsQuery,
    ) -> Result<Marginals, ServiceError> {
        let deadline = Instant::now() + self.wait_timeout();
        let query = Arc::new(query);
        loop {
            let (s, q) = (Arc::clone(&session), Arc::clone(&query));
            let answer = off_async("marginals", move || s.marginals(&q)).await?;
            if let Some(marginals) = answer {
                return Ok(marginals);
            }
            if Instant::now() >= deadline {
                return Err(ServiceError::unavailable(
                    "solving",
                    format!(
                        "session `{}` is being solved; ask again when the solve finishes",
                        session.name
                    ),
                    1,
                ));
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    }
}
