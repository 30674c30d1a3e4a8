//! `set_auto_optimize`: when the session re-optimises by itself.

use crate::api::{AutoOptimizeSet, ServiceError, SetAutoOptimize};
use crate::service::{Caller, Service};

impl Service {
    pub(super) fn set_auto_optimize(
        &self,
        caller: &Caller,
        request: SetAutoOptimize,
    ) -> Result<AutoOptimizeSet, ServiceError> {
        let session = self.writable_as(caller, &request.session)?;
        session.set_auto_optimize(request.auto_optimize)?;
        Ok(AutoOptimizeSet {
            session: session.name.clone(),
            auto_optimize: request.auto_optimize,
        })
    }
}
