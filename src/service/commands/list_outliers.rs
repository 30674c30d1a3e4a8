//! `list_outliers`: a session's possibly wrong loop closures, accepted, pending and rejected.

use crate::api::outliers::OutliersReport;
use crate::api::{ListOutliers, ServiceError};
use crate::service::{Caller, Service};

impl Service {
    pub(super) fn list_outliers(
        &self,
        caller: &Caller,
        request: ListOutliers,
    ) -> Result<OutliersReport, ServiceError> {
        Ok(self.session_as(caller, &request.session)?.outliers_report())
    }
}
