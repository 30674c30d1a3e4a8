//! The reply of each [`super::Command`], one named type per command (those not already wire
//! types such as `SessionInfo` or `Estimate`): the OpenAPI document, the JSON Schemas and the
//! Python client's `TypedDict`s are checked against these (`tests/api/openapi.rs`,
//! `tests/api/command_types.rs`).

use serde::Serialize;

use crate::api::wire::{AutoOptimize, BatchAck, ProducerStatus, SessionInfo, SessionStats};

/// `health`: the service's load.
#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct Health {
    pub status: &'static str,
    pub version: &'static str,
    pub workers: usize,
    pub busy_workers: usize,
    pub queued: usize,
    pub sessions: usize,
    pub session_kinds: Vec<&'static str>,
    pub uptime_seconds: f64,
}

/// `list_sessions`, sorted by name.
#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct SessionList {
    pub sessions: Vec<SessionInfo>,
}

/// `delete_session`.
#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct Deleted {
    pub deleted: String,
}

/// `apply_batch`.
#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct Accepted {
    #[serde(flatten)]
    pub ack: BatchAck,
    /// With `wait`: whether the estimate now reflects this batch (false when no solve was due
    /// under the auto-optimise policy, the solve failed — see `last_error` —, or the wait
    /// timed out).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub solved: Option<bool>,
    /// With `wait`, in a session with a latency budget: whether the estimate reflects this batch
    /// exactly (`false`: provisionally, the exact answer follows as a correction).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub exact: Option<bool>,
    /// With `exact`: the highest sequence the exact estimate reflects.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub exact_sequence: Option<u64>,
}

/// `optimize`.
#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct Optimizing {
    pub session: String,
    pub sequence: u64,
    /// With `wait`: the session's statistics after the solve.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stats: Option<Box<SessionStats>>,
}

/// `set_auto_optimize`: the new policy.
#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct AutoOptimizeSet {
    pub session: String,
    pub auto_optimize: AutoOptimize,
}

/// `cancel`: whether a solve was running.
#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct Cancelled {
    pub session: String,
    pub cancelled: bool,
}

/// `list_producers`: every producer that sent the session a numbered batch, by id.
#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct ProducerList {
    pub session: String,
    pub producers: Vec<ProducerStatus>,
}
