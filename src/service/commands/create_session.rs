//! `create_session`: the request's factor types compiled, then the session registered
//! (`Service::register_session`) for `caller`'s token.

use crate::api::catalogue;
use crate::api::wire::{CreateSession, SessionInfo};
use crate::api::ServiceError;
use crate::service::{off_async, Caller, Service};
use crate::session::factor_types::FactorTypes;

impl Service {
    pub(super) async fn create_session(
        &self,
        caller: &Caller,
        request: CreateSession,
    ) -> Result<SessionInfo, ServiceError> {
        // The configuration's types first, then the request's, compiled (their Jacobians
        // checked numerically, tens of milliseconds for the largest) off the async threads.
        let factor_types = match catalogue::session_kind(&request.kind) {
            Some(kind) => {
                let server_wide = self.server_factor_types.get().cloned().unwrap_or_default();
                let definitions = request.factor_types.clone();
                let compiler = self.type_compiler.clone();
                let compiled = off_async("factor types", move || {
                    FactorTypes::for_new_session(compiler, kind, &server_wide, &definitions)
                })
                .await?;
                Some(compiled)
            }
            None => None,
        };
        self.register_session(request, factor_types, caller.owner_of_new())
    }
}
