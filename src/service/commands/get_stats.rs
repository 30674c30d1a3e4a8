//! `get_stats`: the session's state and statistics.

use crate::api::wire::SessionStats;
use crate::api::{GetStats, ServiceError};
use crate::service::{Caller, Service};

impl Service {
    pub(super) fn get_stats(
        &self,
        caller: &Caller,
        request: GetStats,
    ) -> Result<Box<SessionStats>, ServiceError> {
        let mut stats = self.session_as(caller, &request.session)?.stats();
        stats.instance = self.owning_instance();
        Ok(Box::new(stats))
    }
}
