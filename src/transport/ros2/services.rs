//! The binding's ROS 2 services, `std_srvs/srv/Trigger` under the binding's
//! `service_namespace`, served as rmw_zenoh serves a service: a queryable on
//! `<domain>/<service>/std_srvs::srv::dds_::Trigger_/<service type hash>`, a liveliness token
//! of kind `SS` (so `ros2 service list` sees them), and each reply carrying the request's
//! sequence number and client GID in its attachment (how the client matches replies).
//!
//! - `<ns>/optimize`: solves now and waits; `message` is the solve's outcome (χ², iterations).
//! - `<ns>/export`: `message` is the optimised trajectory as TUM text (`estimate?format=tum`).
//! - `<ns>/reset`: deletes the session and creates it again, empty, with the same kind,
//!   solver options, auto-optimise policy and binding (its user-defined factor types and
//!   `robots` options are not kept: a ROS binding's pose graph has no use for them). The new
//!   session is bound afresh (its node rejoins the graph); this binding ends.
//!
//! Requests go through the one command API as any client's; `success` is false with the
//! error's message when a command is refused.

use std::sync::{Arc, LazyLock};

use serde::{Deserialize, Serialize};
use zenoh::query::Query;

use super::attachment::Attachment;
use super::cdr_codec;
use super::messages::RosType;
use super::type_hash;
use crate::api::export::EstimateFormat;
use crate::api::wire::EstimateQuery;
use crate::api::{DeleteSession, Optimize};
use crate::service::{Caller, Command, Recording, Reply, Service, ServiceError};

/// `std_srvs/srv/Trigger`, its hash computed from its `.srv` as rosidl does.
pub static TRIGGER: LazyLock<RosType> = LazyLock::new(|| RosType {
    name: "std_srvs/srv/Trigger",
    dds_name: "std_srvs::srv::dds_::Trigger_",
    hash: type_hash::service_rihs01(type_hash::TRIGGER, type_hash::STANDARD)
        .expect("Trigger refers only to known types (type_hash's tests)")
        .leak(),
});

/// `std_srvs/srv/Trigger_Response`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TriggerResponse {
    pub success: bool,
    pub message: String,
}

/// What a service does.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Action {
    Optimize,
    Export,
    Reset,
}

impl Action {
    pub const ALL: [Action; 3] = [Action::Optimize, Action::Export, Action::Reset];

    /// The service's name under the namespace.
    pub fn name(self) -> &'static str {
        match self {
            Action::Optimize => "optimize",
            Action::Export => "export",
            Action::Reset => "reset",
        }
    }
}

/// What the services run with.
#[derive(Clone)]
pub(super) struct Server {
    pub service: Arc<Service>,
    pub caller: Arc<Caller>,
    pub session: String,
    pub binding: crate::api::ros2::Ros2Binding,
}

impl Server {
    /// Answers `query` to `action`'s service.
    pub async fn answer(&self, action: Action, query: Query) {
        // rmw_zenoh's client sends its request's sequence number and GID, and matches the
        // reply by them.
        let request = query
            .attachment()
            .and_then(|a| Attachment::decode(&a.to_bytes()).ok());
        let Some(request) = request else {
            let _ = query
                .reply_err("not an rmw_zenoh request: no attachment")
                .await;
            return;
        };
        let response = match action {
            Action::Reset => {
                // This binding ends with the session it deletes: answer from a task of its own.
                let server = self.clone();
                tokio::spawn(async move {
                    let response = server.reset().await;
                    reply(query, request, &response).await;
                });
                return;
            }
            Action::Optimize => self.optimize().await,
            Action::Export => self.export().await,
        };
        reply(query, request, &response).await;
    }

    async fn execute(&self, command: Command) -> Result<Reply, ServiceError> {
        self.service
            .execute(&self.caller, command, Recording::History)
            .await
    }

    async fn optimize(&self) -> TriggerResponse {
        let command = Command::Optimize(Optimize {
            session: self.session.clone(),
            wait: true,
            after: Default::default(),
        });
        match self.execute(command).await {
            Ok(Reply::Optimizing(optimizing)) => {
                let message = match optimizing.stats.and_then(|s| s.last_summary) {
                    Some(summary) => format!(
                        "chi2 {} after {} iterations ({})",
                        summary.final_chi2, summary.iterations, summary.termination.message
                    ),
                    None => format!("optimised at sequence {}", optimizing.sequence),
                };
                done(message)
            }
            Ok(_) => failed("the optimisation answered something else".into()),
            Err(e) => failed(e.body.message),
        }
    }

    async fn export(&self) -> TriggerResponse {
        let query = EstimateQuery {
            format: Some(EstimateFormat::Tum),
            ..EstimateQuery::default()
        };
        match self
            .execute(Command::get_estimate(self.session.clone(), query))
            .await
        {
            Ok(Reply::Export(export)) => done(export.body),
            Ok(_) => failed("the export answered something else".into()),
            Err(e) => failed(e.body.message),
        }
    }

    async fn reset(&self) -> TriggerResponse {
        let session = self.session.clone();
        // Created again as it is configured now: options, policies, budget, robots, and the
        // factor types it holds (a robot's later batches may use them), bound again.
        let live = match self.service.session(&session) {
            Ok(live) => live,
            Err(e) => return failed(e.body.message),
        };
        let mut create = live.creation_record();
        drop(live);
        create.ros2 = Some(Box::new(self.binding.clone()));
        let delete = Command::DeleteSession(DeleteSession {
            session: session.clone(),
        });
        if let Err(e) = self.execute(delete).await {
            return failed(e.body.message);
        }
        match self.execute(Command::CreateSession(create)).await {
            Ok(_) => done(format!("session {session} reset: empty, bound again")),
            Err(e) => failed(format!(
                "session {session} was deleted but not created again: {}",
                e.body.message
            )),
        }
    }
}

fn done(message: String) -> TriggerResponse {
    TriggerResponse {
        success: true,
        message,
    }
}

fn failed(message: String) -> TriggerResponse {
    TriggerResponse {
        success: false,
        message,
    }
}

/// The response, on the query's key, with the request's sequence number and client GID.
async fn reply(query: Query, request: Attachment, response: &TriggerResponse) {
    let attachment = Attachment::stamped_now(request.sequence_number, request.source_gid);
    let key = query.key_expr().clone();
    let sent = query
        .reply(key, cdr_codec::encode(response))
        .attachment(attachment.encode().to_vec())
        .await;
    if let Err(e) = sent {
        tracing::debug!("ROS service reply failed: {e}");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_trigger_type_is_jazzys_and_its_response_is_cdr() {
        assert_eq!(
            TRIGGER.hash,
            "RIHS01_eeff2cd6fa5ad9d27cdf4dec64818317839b62f212a91e6b5304b634b2062c5f"
        );
        let bytes = cdr_codec::encode(&done("ok".into()));
        // header, bool, padding to 4, length 3 (with the NUL), "ok\0".
        assert_eq!(bytes, [0, 1, 0, 0, 1, 0, 0, 0, 3, 0, 0, 0, b'o', b'k', 0]);
    }
}
