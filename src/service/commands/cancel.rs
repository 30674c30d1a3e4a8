//! `cancel`: stop the running solve after its current iteration.

use crate::api::{Cancel, Cancelled, ServiceError};
use crate::service::{Caller, Service};

impl Service {
    pub(super) fn cancel(
        &self,
        caller: &Caller,
        request: Cancel,
    ) -> Result<Cancelled, ServiceError> {
        let session = self.session_as(caller, &request.session)?;
        Ok(Cancelled {
            cancelled: session.cancel(),
            session: session.name.clone(),
        })
    }
}
