//! `list_robots`: a session's robots, where their frames sit, and its held, rejected and merged
//! closures.

use crate::api::robots::RobotsReport;
use crate::api::{ListRobots, ServiceError};
use crate::service::{Caller, Service};

impl Service {
    pub(super) fn list_robots(
        &self,
        caller: &Caller,
        request: ListRobots,
    ) -> Result<RobotsReport, ServiceError> {
        self.session_as(caller, &request.session)?.robots_report()
    }
}
