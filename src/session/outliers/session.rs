//! The session's side of its candidates: the policy at creation and the report.

use super::Outliers;
use crate::api::outliers::{OutlierPolicy, OutliersReport};
use crate::api::ServiceError;
use crate::session::Session;

impl Session {
    /// Sets a new (empty) session's policy for unmarked loop closures; graph kinds only.
    pub fn set_outlier_policy(&self, policy: OutlierPolicy) -> Result<(), ServiceError> {
        if policy != OutlierPolicy::Off && self.kind.name == crate::api::catalogue::SLIDING_WINDOW {
            return Err(ServiceError::bad_request(
                "invalid_value",
                "outliers",
                "a sliding window takes fusion messages, not loop closures: outliers is for graph sessions",
            ));
        }
        self.lock().outliers = Outliers::new(policy);
        Ok(())
    }

    pub fn outlier_policy(&self) -> OutlierPolicy {
        self.lock().outliers.policy
    }

    /// `list_outliers`: the candidates, accepted, pending and rejected.
    pub fn outliers_report(&self) -> OutliersReport {
        self.lock().outliers.report(&self.name)
    }
}
