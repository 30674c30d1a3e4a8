//! `get_estimate`: the estimate (after the producer's batches it names) as JSON, or as a file
//! (`tum`, `kitti`, `g2o`, `ply`).

use crate::api::export::EstimateFormat;
use crate::api::wire::EstimateQuery;
use crate::api::{GetEstimate, Reply, ServiceError};
use crate::service::{Caller, Service};

impl Service {
    pub(super) async fn get_estimate(
        &self,
        caller: &Caller,
        request: GetEstimate,
    ) -> Result<Reply, ServiceError> {
        let session = self.session_as(caller, &request.session)?;
        super::wait_after(&session, request.after.resolve()?).await?;
        let mut query = EstimateQuery {
            since: request.since,
            from: request.from,
            to: request.to,
            robot: request.robot,
            frame: request.frame,
            ..EstimateQuery::default()
        };
        session.resolve_robot_query(&mut query)?;
        match request.format.unwrap_or_default() {
            EstimateFormat::Json => Ok(Reply::Estimate(session.estimate(&query))),
            file => Ok(Reply::Export(session.export(file, &query)?)),
        }
    }
}
