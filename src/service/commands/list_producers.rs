//! `list_producers`: where every producer that sent the session a numbered batch stands.

use crate::api::{ListProducers, ProducerList, ServiceError};
use crate::service::{Caller, Service};

impl Service {
    pub(super) fn list_producers(
        &self,
        caller: &Caller,
        request: ListProducers,
    ) -> Result<ProducerList, ServiceError> {
        let session = self.session_as(caller, &request.session)?;
        let producers = session.progress().producers.into_keys();
        Ok(ProducerList {
            producers: producers.map(|p| session.producer_status(&p)).collect(),
            session: request.session,
        })
    }
}
