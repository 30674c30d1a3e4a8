//! The JSON messages of the session API, shared by every transport (schemas in `proto/v1/`).

use serde::{Deserialize, Serialize};

use super::outliers::OutlierPolicy;

use super::wire_list;
use crate::factors::RobustKernel;
use crate::problem::Key;
use crate::solver::{SolverOptions, Summary};
use crate::wire_number;

/// Server-assigned id of an accepted factor, used to remove it.
pub type FactorId = u64;

/// When a session re-optimises by itself. (The field-less policies are empty struct variants:
/// serde lets unit variants of a tagged enum through with any extra fields.)
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(tag = "policy", rename_all = "snake_case", deny_unknown_fields)]
pub enum AutoOptimize {
    /// After every accepted batch (updates arriving during a solve are coalesced into the next).
    EveryBatch {},
    /// Once at least `factors` factors have arrived since the last solve.
    EveryNFactors {
        #[serde(deserialize_with = "wire_number::usize")]
        factors: usize,
    },
    /// At most once every `milliseconds` while updates keep arriving.
    EveryMs {
        #[serde(deserialize_with = "wire_number::u64")]
        milliseconds: u64,
    },
    /// Only when asked (`optimize`).
    Manual {},
}

impl Default for AutoOptimize {
    fn default() -> Self {
        Self::EveryBatch {}
    }
}

#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CreateSession {
    /// Session name: 1–64 characters of `[A-Za-z0-9_-]`; generated when absent.
    #[serde(default)]
    pub session: Option<String>,
    pub kind: String,
    /// Solver options: the fields given, the kind's defaults for the others (LM damped from
    /// the first step for bundle adjustment, whatever fields are given).
    #[serde(default)]
    #[schema(value_type = Option<SolverOptions>)]
    pub options: Option<super::given_options::GivenSolverOptions>,
    #[serde(default)]
    pub auto_optimize: AutoOptimize,
    /// Factor types of this session's own, each a residual written as an expression and
    /// differentiated automatically; batches then use their names as `type` (see
    /// docs/guide/factor-types.md, "User-defined factors"). Graph kinds only.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub factor_types: Vec<crate::factors::expression::FactorTypeDefinition>,
    /// Bind the session to ROS 2 topics of robots that speak rmw_zenoh (odometry, priors and,
    /// for a `sliding_window`, IMU in; the optimised path, pose and `map → odom` out);
    /// `pose_graph_3d` and `sliding_window`. See docs/guide/ros2.md. Boxed: most requests have
    /// none, and a command holds its request.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ros2: Option<Box<super::ros2::Ros2Binding>>,
    /// The session holds several robots, each in its own odometry frame until closures between
    /// them agree (`{}` for the defaults); pose graph kinds. See docs/guide/many-robots.md.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub robots: Option<super::robots::RobotsOptions>,
    /// `auto`: every loop closure may be wrong (as if marked `"outlier": "auto"`), and wrong
    /// ones are held out of the estimate; `off` (default): only marked factors. Graph kinds.
    #[serde(default, skip_serializing_if = "OutlierPolicy::is_off")]
    pub outliers: OutlierPolicy,
    /// A latency budget for updates, in milliseconds (1–60000; graph kinds): an update the
    /// exact solve has not reflected in time (at most a tenth of it) is answered
    /// provisionally, and the exact answer follows as a correction (docs/guide/latency.md).
    /// Absent: every answer is exact.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_update_ms: Option<u64>,
}

#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct VariableSpec {
    #[serde(deserialize_with = "wire_number::u64")]
    pub key: Key,
    pub kind: String,
    /// Initial guess in the kind's wire encoding; when absent it is predicted from a factor of the
    /// same batch that connects it to a known variable (odometry), else the batch is rejected.
    #[serde(default)]
    pub value: Option<Vec<f64>>,
    #[serde(default)]
    pub fixed: bool,
    /// When the pose was taken, in seconds on the robot's clock (e.g. a ROS header stamp).
    /// Trajectory exports (`estimate?format=tum`) write it; finite, set once with the variable.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stamp: Option<f64>,
}

#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct FactorSpec {
    #[serde(rename = "type")]
    pub factor_type: String,
    #[serde(deserialize_with = "wire_number::u64_list")]
    pub keys: Vec<Key>,
    pub measurement: Vec<f64>,
    /// Information matrix, row-major n×n or its upper triangle row by row (n(n+1)/2 values, g2o's
    /// order). Exactly one of `information` and `sigmas` must be given.
    #[serde(default)]
    pub information: Option<Vec<f64>>,
    /// Standard deviations (diagonal noise), one per residual.
    #[serde(default)]
    pub sigmas: Option<Vec<f64>>,
    #[serde(default)]
    pub robust: Option<RobustKernel>,
    /// `auto`: the factor may be wrong (a loop closure from place recognition); the service
    /// decides whether it enters the estimate (`GET /v1/sessions/{s}/outliers`). `trusted`:
    /// never held out, whatever the session's `outliers` policy.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub outlier: Option<super::outliers::OutlierMark>,
}

#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct GuessSpec {
    #[serde(deserialize_with = "wire_number::u64")]
    pub key: Key,
    pub value: Vec<f64>,
}

/// One atomic update: validated whole, applied whole or not at all.
#[derive(Clone, Debug, Default, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Batch {
    #[serde(default, deserialize_with = "wire_list::items")]
    pub variables: Vec<VariableSpec>,
    #[serde(default, deserialize_with = "wire_list::items")]
    pub factors: Vec<FactorSpec>,
    #[serde(default, deserialize_with = "wire_list::key_items")]
    pub remove_factors: Vec<FactorId>,
    #[serde(default, deserialize_with = "wire_list::key_items")]
    pub fix: Vec<Key>,
    #[serde(default, deserialize_with = "wire_list::key_items")]
    pub unfix: Vec<Key>,
    /// New values for existing variables.
    #[serde(default, deserialize_with = "wire_list::items")]
    pub guesses: Vec<GuessSpec>,
    /// Who sent it, for exactly-once ingest (with `producer_seq`): a stable id of the robot or
    /// program, 1 to 64 characters of `A-Z a-z 0-9 . _ -`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub producer: Option<String>,
    /// The producer's own counter, 1, 2, 3, … without gaps. A repeat is answered with the
    /// original acknowledgement (`duplicate`) and applied no second time; a gap is refused
    /// (409 `producer_sequence_gap`, naming the number expected).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "wire_number::optional_u64"
    )]
    pub producer_seq: Option<u64>,
}

#[derive(Clone, Debug, Serialize, Deserialize, utoipa::ToSchema)]
pub struct BatchAck {
    pub session: String,
    pub sequence: u64,
    /// Ids of the batch's factors, in the order given.
    pub factor_ids: Vec<FactorId>,
    /// Keys whose initial guess was predicted from a factor.
    pub predicted: Vec<Key>,
    /// The estimate already reflects this batch: its new factors could not lower chi2 by more
    /// than the function tolerance, so no solve is needed (otherwise a `summary` event with a
    /// sequence at least this one follows the solve).
    pub reflected: bool,
    /// The batch's `producer` and `producer_seq`, when it had them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub producer: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub producer_seq: Option<u64>,
    /// Cumulative: every batch of this producer up to this number is applied (with a
    /// producer). A client that lost acknowledgements learns from any later one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub accepted_through: Option<u64>,
    /// A repeat of a batch applied before: this is its original acknowledgement, and nothing
    /// was applied now.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub duplicate: bool,
}

/// Where a producer's batches stand in a session (`producer_status`; also what a `lagged`
/// event carries for every producer).
#[derive(Clone, Debug, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ProducerStatus {
    pub session: String,
    pub producer: String,
    /// Every batch of this producer up to this number is applied (0: none).
    pub accepted_through: u64,
    /// The session sequence of that producer's last applied batch (0: none).
    pub sequence: u64,
    /// The session sequence the estimate reflects: the producer's batches up to `sequence`
    /// are reflected when this is at least `sequence`.
    pub reflected_sequence: u64,
}

/// Which part of the estimate to read (from a query string or selector; the rpc's JSON form is
/// `Command::GetEstimate`).
#[derive(Clone, Debug, Default, Deserialize, Serialize, utoipa::ToSchema, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct EstimateQuery {
    /// Only variables changed after this sequence number.
    #[serde(default)]
    pub since: Option<u64>,
    /// Key range, inclusive.
    #[serde(default)]
    pub from: Option<Key>,
    #[serde(default)]
    pub to: Option<Key>,
    /// Answer only once this producer's batches up to `after_seq` are applied (see `After`).
    #[serde(default)]
    pub after_producer: Option<String>,
    #[serde(default)]
    pub after_seq: Option<u64>,
    #[serde(default)]
    pub after_timeout_ms: Option<u64>,
    /// `json` (default) or a trajectory/point file: `tum`, `kitti`, `g2o`, `ply` (text; see
    /// `api::export`) of the variables `from`/`to` (and in graph sessions `since`) select.
    #[serde(default)]
    pub format: Option<super::export::EstimateFormat>,
    /// Only this robot's poses (a session with `robots`: its keys' character, e.g. `b`).
    #[serde(default)]
    pub robot: Option<String>,
    /// The frame `robot`'s poses are read in: `map` (default) or its own `odom`.
    #[serde(default)]
    pub frame: Option<super::robots::RobotFrame>,
}

/// "After my batches": a request (`optimize`, an estimate read) that first waits until the
/// session has applied `producer`'s batches up to `seq`, whichever transport they travelled on,
/// at most `timeout` (503 `after_timeout` then).
#[derive(Clone, Debug, PartialEq)]
pub struct After {
    pub producer: String,
    pub seq: u64,
    pub timeout: std::time::Duration,
}

impl After {
    /// How long an `after` waits when the request does not say.
    pub const DEFAULT_TIMEOUT_MS: u64 = 10_000;
    /// The longest it may be asked to wait.
    pub const MAX_TIMEOUT_MS: u64 = 60_000;

    /// From the request's `after_producer`, `after_seq` and `after_timeout_ms`: both of the
    /// first two or neither; the timeout within [`Self::MAX_TIMEOUT_MS`].
    pub fn from_fields(
        producer: Option<String>,
        seq: Option<u64>,
        timeout_ms: Option<u64>,
    ) -> Result<Option<After>, crate::api::ServiceError> {
        use crate::api::ServiceError;
        let timeout_ms = timeout_ms.unwrap_or(Self::DEFAULT_TIMEOUT_MS);
        if timeout_ms > Self::MAX_TIMEOUT_MS {
            return Err(ServiceError::bad_request(
                "invalid_value",
                "after_timeout_ms",
                format!("after_timeout_ms is at most {}", Self::MAX_TIMEOUT_MS),
            ));
        }
        match (producer, seq) {
            (None, None) => Ok(None),
            (Some(producer), Some(seq)) => Ok(Some(After {
                producer,
                seq,
                timeout: std::time::Duration::from_millis(timeout_ms),
            })),
            (Some(_), None) => Err(ServiceError::bad_request(
                "missing_after_seq",
                "after_seq",
                "after_producer needs after_seq: the producer sequence to wait for",
            )),
            (None, Some(_)) => Err(ServiceError::bad_request(
                "missing_after_producer",
                "after_producer",
                "after_seq needs after_producer: the producer whose batches to wait for",
            )),
        }
    }
}

/// The drawable graph of a session (the web view's data): pose positions in key order with the
/// client's initial guesses, landmark positions, and pose-to-pose factors as key pairs with
/// their χ².
#[derive(Clone, Debug, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Graph {
    pub session: String,
    pub kind: String,
    pub sequence: u64,
    /// 2 for planar sessions (z is 0), else 3.
    pub dimension: u8,
    pub poses: Vec<DrawnVariable>,
    pub points: Vec<DrawnVariable>,
    pub edges: Vec<[Key; 2]>,
    /// Each edge's χ² contribution at the estimate, in the order of `edges` (the web view
    /// colours edges by it); null while a solve holds the problem or for a queued edge. Empty
    /// for sliding windows.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub edge_chi2: Vec<Option<f64>>,
}

#[derive(Clone, Debug, Serialize, Deserialize, utoipa::ToSchema)]
pub struct DrawnVariable {
    pub key: Key,
    pub position: [f64; 3],
    /// Where the client last put it (its initial guess, or a later `guesses` entry).
    pub initial: [f64; 3],
}

pub use super::marginals_wire::{MarginalCovariance, Marginals, MarginalsQuery};

/// A variable's wire value, inline up to an SE(3) pose's 7 numbers. A loop closure in a large
/// map publishes an estimate of most of it; with a heap allocation per value, making and
/// dropping that event was 4–5 % of a 10k stream's time (malloc and free, `perf`).
pub type WireValue = smallvec::SmallVec<[f64; 7]>;

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
pub struct VariableValue {
    pub key: Key,
    pub kind: std::borrow::Cow<'static, str>,
    #[schema(value_type = Vec<f64>)]
    pub value: WireValue,
    /// Sequence number of the update that last changed this value.
    pub changed: u64,
    /// The stamp the variable was created with, if any (seconds).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stamp: Option<f64>,
}

#[derive(Clone, Debug, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Estimate {
    pub session: String,
    /// Every accepted batch up to this sequence number is reflected.
    pub sequence: u64,
    pub variables: Vec<VariableValue>,
}

#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct SessionStats {
    pub session: String,
    pub kind: String,
    /// Last accepted batch.
    pub sequence: u64,
    /// Last batch reflected by a finished solve.
    pub solved_sequence: u64,
    pub num_variables: usize,
    pub num_factors: usize,
    /// Batches accepted during the running solve, waiting to be applied.
    pub pending_batches: usize,
    pub solving: bool,
    pub solves: u64,
    /// Updates whose new factors could not lower chi2 by more than the function tolerance, so
    /// no solve was needed.
    pub skipped_solves: u64,
    #[schema(required = true)]
    pub chi2: Option<f64>,
    pub converged: bool,
    pub auto_optimize: AutoOptimize,
    pub options: SolverOptions,
    #[schema(required = true)]
    pub last_error: Option<String>,
    #[schema(required = true)]
    pub last_summary: Option<Summary>,
    /// Being rebuilt from its journal after a restart (writes get 503 until it is done).
    pub recovering: bool,
    /// Its files could not be recovered whole (a damaged journal or snapshot, an entry that did
    /// not replay): it holds what was recovered, is read-only (409 `session_corrupt`) and says
    /// why in `last_error`; DELETE removes it.
    pub corrupt: bool,
    /// Estimated memory this session holds, in bytes.
    pub memory_bytes: usize,
    /// Names of the factor types declared at creation, when any.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub factor_types: Vec<String>,
    /// In a fleet: the id of the instance that owns the session (and answered).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub instance: Option<String>,
    /// The session's ROS 2 binding (its creation request's, defaults filled in), when it has
    /// one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ros2: Option<Box<super::ros2::Ros2Binding>>,
    /// With a latency budget (`max_update_ms`): provisional answers and their corrections.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub latency: Option<Box<super::latency::LatencyReport>>,
}

#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct SessionInfo {
    pub session: String,
    pub kind: String,
    pub options: SolverOptions,
    pub auto_optimize: AutoOptimize,
    /// Names of the factor types declared at creation, when any.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub factor_types: Vec<String>,
    /// In a fleet: the id of the instance that owns the session.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub instance: Option<String>,
    /// The session's ROS 2 binding (its creation request's, defaults filled in), when it has
    /// one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ros2: Option<Box<super::ros2::Ros2Binding>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_update_ms: Option<u64>,
}

/// What a session streams out (SSE events, zenoh publications).
#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum SessionEvent {
    /// A batch was accepted.
    Ack(BatchAck),
    /// One solver iteration finished.
    Iteration {
        session: String,
        /// The solve's number within the session, and the sequence it works on.
        solve: u64,
        sequence: u64,
        #[serde(flatten)]
        report: crate::solver::IterationReport,
    },
    /// Variables whose value changed, with the sequence they reflect.
    Estimate(Estimate),
    Summary {
        session: String,
        solve: u64,
        sequence: u64,
        summary: Box<Summary>,
    },
    /// A sliding window's newest state after a keyframe's optimisation.
    State {
        session: String,
        state: super::fusion::StateReport,
        iterations: usize,
        /// From the keyframe's arrival to its optimised state, marginalisation included.
        update_seconds: f64,
    },
    /// A sliding window's free keyframes, oldest first, after a keyframe's optimisation.
    Window {
        session: String,
        keyframes: Vec<super::fusion::StateReport>,
        /// The keyframes this optimisation marginalised, oldest first, with their estimate at
        /// it: the lag-smoothed trajectory (each state saw the whole window it leaves).
        #[serde(skip_serializing_if = "Vec::is_empty")]
        smoothed: Vec<super::fusion::StateReport>,
    },
    /// A solve failed (the estimate keeps its last good values), or a streamed batch was rejected.
    Error {
        session: String,
        #[schema(required = true)]
        sequence: Option<u64>,
        error: crate::api::ErrorBody,
        /// The rejected batch's `producer` and `producer_seq`, when it had them.
        #[serde(skip_serializing_if = "Option::is_none")]
        producer: Option<String>,
        #[serde(skip_serializing_if = "Option::is_none")]
        producer_seq: Option<u64>,
    },
    /// This subscriber fell behind and `skipped` events were dropped for it. What it missed is
    /// re-synchronised: this marker carries every producer's cumulative progress (so no
    /// acknowledgement is lost), and an `estimate` event with the latest value of every
    /// variable changed meanwhile follows it. Skipped iteration statistics, summaries and
    /// errors are not repeated.
    Lagged {
        session: String,
        skipped: u64,
        /// The session's latest accepted sequence.
        sequence: u64,
        /// The sequence the estimate reflects.
        reflected_sequence: u64,
        /// Every producer's `accepted_through`.
        producers: std::collections::BTreeMap<String, u64>,
    },
    /// Two components of a session's robots merged (see `GET /v1/sessions/{s}/robots`).
    Merge {
        session: String,
        #[serde(flatten)]
        merge: super::robots::MergeReport,
    },
    /// A solve decided possibly wrong loop closures: which entered the estimate and which are
    /// held out (see `GET /v1/sessions/{s}/outliers`).
    Outliers {
        session: String,
        #[serde(flatten)]
        decisions: super::outliers::OutlierDecisions,
    },
}

impl SessionEvent {
    /// The zenoh topic (`factord/<session>/out/<topic>`) and SSE event name.
    pub fn topic(&self) -> &'static str {
        match self {
            Self::Ack(_) => "acks",
            Self::Iteration { .. } => "stats",
            Self::Estimate(_) => "poses",
            Self::Summary { .. } => "summary",
            Self::State { .. } => "state",
            Self::Window { .. } => "window",
            Self::Error { .. } => "errors",
            Self::Lagged { .. } => "lagged",
            Self::Merge { .. } => "merges",
            Self::Outliers { .. } => "outliers",
        }
    }
}

#[cfg(test)]
mod tests {
    /// Internally tagged enums replay buffered content; whole floats must get through that too.
    #[test]
    fn whole_floats_reach_fields_inside_tagged_enums() {
        use super::super::fusion::FusionMessage;
        use super::AutoOptimize;
        let policy: AutoOptimize =
            serde_json::from_str(r#"{"policy": "every_ms", "milliseconds": 283.0}"#).unwrap();
        assert_eq!(policy, AutoOptimize::EveryMs { milliseconds: 283 });
        let message: FusionMessage = serde_json::from_str(
            r#"{"type": "position_prior", "key": 4.0, "position": [0, 0, 0], "sigma": 1}"#,
        )
        .unwrap();
        assert!(matches!(
            message,
            FusionMessage::PositionPrior { key: 4, .. }
        ));
        assert!(serde_json::from_str::<AutoOptimize>(
            r#"{"policy": "every_n_factors", "factors": 2.5}"#
        )
        .is_err());
    }

    /// A batch holds up to `max_batch_items` messages, most of them IMU samples of ~55 bytes of
    /// JSON: each element must stay near that size, so the large messages are boxed.
    #[test]
    fn a_fusion_message_in_a_batch_costs_little_more_than_an_imu_sample() {
        let size = std::mem::size_of::<super::super::fusion::FusionMessage>();
        assert!(size <= 128, "FusionMessage is {size} bytes");
    }

    #[test]
    fn boxed_fusion_messages_read_and_write_the_same_wire_form() {
        use super::super::fusion::FusionMessage;
        let start = r#"{"type":"start","t":1.0,"position":[0,0,0],"rotation_xyzw":[0,0,0,1],"sigmas":{"rotation":0.1,"position":0.1,"velocity":0.1,"accel_bias":0.1,"gyro_bias":0.1}}"#;
        let message: FusionMessage = serde_json::from_str(start).unwrap();
        let back = serde_json::to_value(&message).unwrap();
        assert_eq!(back["type"], "start");
        assert_eq!(back["window"], 10);
        let unknown = start.replace(r#""t":1.0"#, r#""t":1.0,"extra":1"#);
        assert!(serde_json::from_str::<FusionMessage>(&unknown).is_err());
    }
}
