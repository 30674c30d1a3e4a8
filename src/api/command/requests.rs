//! The request of each [`super::Command`] that carries fields, one named struct per command
//! (`Command::Optimize(Optimize)`): what an rpc sends after its `op`, what an HTTP handler
//! builds from its path, query and body. `CreateSession` is in `wire` (journalled too).

use serde::{Deserialize, Serialize};

use crate::api::wire::{After, AutoOptimize, Batch};
use crate::api::ServiceError;
use crate::problem::Key;
use crate::wire_number;

// Flat in the request (`serde(flatten)`); `resolve` checks them into an `After`. Query strings
// (`EstimateQuery`, HTTP `optimize`) spell the three out: a flattened struct would read a query
// string's numbers as text.
/// "After my batches": `after_producer`, `after_seq` (both or neither) and `after_timeout_ms`.
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq, utoipa::ToSchema)]
pub struct AfterFields {
    /// Wait first until this producer's batches up to `after_seq` are applied, whichever
    /// transport they travelled on (at most `after_timeout_ms`, default 10000: 503
    /// `after_timeout`).
    #[serde(default)]
    pub after_producer: Option<String>,
    #[serde(default, deserialize_with = "wire_number::optional_u64")]
    pub after_seq: Option<u64>,
    #[serde(default, deserialize_with = "wire_number::optional_u64")]
    pub after_timeout_ms: Option<u64>,
}

impl AfterFields {
    /// Both of producer and seq or neither, the timeout within bounds (see [`After`]).
    pub fn resolve(self) -> Result<Option<After>, ServiceError> {
        After::from_fields(self.after_producer, self.after_seq, self.after_timeout_ms)
    }
}

/// Delete a session (its files too).
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct DeleteSession {
    pub session: String,
}

/// Add variables and factors, remove factors, fix/unfix, set guesses — atomically.
/// With `wait`, answers once the estimate reflects the batch (when a solve is due).
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ApplyBatch {
    pub session: String,
    pub batch: Batch,
    #[serde(default)]
    pub wait: bool,
}

/// Solve now whatever the policy; with `wait`, answer when it has finished.
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Optimize {
    pub session: String,
    #[serde(default)]
    pub wait: bool,
    #[serde(flatten)]
    pub after: AfterFields,
}

/// Change when the session re-optimises by itself.
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct SetAutoOptimize {
    pub session: String,
    pub auto_optimize: AutoOptimize,
}

/// Declare more user-defined factor types in a running graph session (all or none);
/// answers the session's info with every declared name.
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct DefineFactorTypes {
    pub session: String,
    pub factor_types: Vec<crate::factors::expression::FactorTypeDefinition>,
}

/// Read the estimate: every variable, those changed after `since`, a key range, or a file.
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct GetEstimate {
    pub session: String,
    #[serde(default, deserialize_with = "wire_number::optional_u64")]
    pub since: Option<u64>,
    #[serde(default, deserialize_with = "wire_number::optional_u64")]
    pub from: Option<Key>,
    #[serde(default, deserialize_with = "wire_number::optional_u64")]
    pub to: Option<Key>,
    #[serde(flatten)]
    pub after: AfterFields,
    /// `json` (default), or a file: `tum`, `kitti`, `g2o`, `ply` (see `api::export`).
    #[serde(default)]
    pub format: Option<crate::api::export::EstimateFormat>,
    /// Only this robot's poses, in the map or its own odometry frame (sessions with `robots`).
    #[serde(default)]
    pub robot: Option<String>,
    #[serde(default)]
    pub frame: Option<crate::api::robots::RobotFrame>,
}

/// Where a producer's batches stand in a session (exactly-once ingest).
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ProducerQuery {
    pub session: String,
    pub producer: String,
}

/// Every producer that sent the session a numbered batch, and where its batches stand.
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ListProducers {
    pub session: String,
}

/// The session's robots, their components and frames, held and rejected closures, merges.
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ListRobots {
    pub session: String,
}

/// The session's possibly wrong loop closures: accepted, pending and rejected.
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ListOutliers {
    pub session: String,
}

/// The session's statistics.
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct GetStats {
    pub session: String,
}

/// Stop the running solve after its current iteration.
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Cancel {
    pub session: String,
}

/// IMU samples, keyframes, relative poses and priors for a `sliding_window` session.
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Fusion {
    pub session: String,
    pub messages: Vec<crate::api::fusion::FusionMessage>,
}

/// What the web view draws: positions, initial guesses and pose-to-pose edges.
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct GetGraph {
    pub session: String,
}

/// The session's timeline of solves, recent events and rejected inputs (the web view's
/// history, kept bounded in memory).
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct GetHistory {
    pub session: String,
}

/// Marginal covariances of `keys` at the current estimate (and their joint covariance).
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct GetMarginals {
    pub session: String,
    #[serde(deserialize_with = "wire_number::u64_list")]
    pub keys: Vec<Key>,
    #[serde(default)]
    pub joint: bool,
}
