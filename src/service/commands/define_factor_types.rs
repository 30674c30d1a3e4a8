//! `define_factor_types`: more user-defined factor types in a running graph session (all or
//! none), answered with the session's info.

use crate::api::wire::SessionInfo;
use crate::api::{DefineFactorTypes, ServiceError};
use crate::service::{off_async, Caller, Service};

impl Service {
    pub(super) async fn define_factor_types(
        &self,
        caller: &Caller,
        request: DefineFactorTypes,
    ) -> Result<SessionInfo, ServiceError> {
        let session = self.writable_as(caller, &request.session)?;
        let definitions = request.factor_types;
        // Compiling checks each definition's Jacobian numerically: off the async threads.
        off_async("factor types", move || {
            session.define_factor_types(definitions)
        })
        .await
    }
}
