//! `get_graph`: what the web view draws.

use crate::api::wire::Graph;
use crate::api::{GetGraph, ServiceError};
use crate::service::{Caller, Service};

impl Service {
    pub(super) fn get_graph(
        &self,
        caller: &Caller,
        request: GetGraph,
    ) -> Result<Box<Graph>, ServiceError> {
        Ok(Box::new(self.session_as(caller, &request.session)?.graph()))
    }
}
