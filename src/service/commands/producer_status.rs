//! `producer_status`: where one producer's batches stand (exactly-once ingest).

use crate::api::wire::ProducerStatus;
use crate::api::{ProducerQuery, ServiceError};
use crate::service::{Caller, Service};

impl Service {
    pub(super) fn producer_status(
        &self,
        caller: &Caller,
        request: ProducerQuery,
    ) -> Result<ProducerStatus, ServiceError> {
        let session = self.session_as(caller, &request.session)?;
        crate::session::check_producer_id(&request.producer, "producer")?;
        Ok(session.producer_status(&request.producer))
    }
}
