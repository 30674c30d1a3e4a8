//! `get_history`: the session's timeline of solves, recent events and rejected inputs.

use crate::api::history::SessionHistory;
use crate::api::{GetHistory, ServiceError};
use crate::service::{Caller, Service};

impl Service {
    pub(super) fn get_history(
        &self,
        caller: &Caller,
        request: GetHistory,
    ) -> Result<Box<SessionHistory>, ServiceError> {
        Ok(Box::new(
            self.session_as(caller, &request.session)?.history(),
        ))
    }
}
