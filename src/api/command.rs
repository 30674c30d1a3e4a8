//! The command API's wire form: every operation both transports send ([`Command`]; zenoh:
//! this JSON on `factord/rpc`), what it answers ([`Reply`]), and how an rpc payload is decoded
//! into one ([`parse_command`]). What a command does is the service's
//! (`Service::execute_as`, a layer above: not linked from here).

use serde::{Deserialize, Serialize};

use super::decode::{parse_json, parse_json_within};
use super::error::ServiceError;
use crate::api::wire::*;
use crate::problem::Key;
use crate::wire_number;

/// Every operation of the API, as both transports send it (zenoh: this JSON on `factord/rpc`).
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(tag = "op", rename_all = "snake_case", deny_unknown_fields)]
pub enum Command {
    Health,
    ListSessions,
    CreateSession(CreateSession),
    DeleteSession {
        session: String,
    },
    /// Add variables and factors, remove factors, fix/unfix, set guesses — atomically.
    /// With `wait`, answers once the estimate reflects the batch (when a solve is due).
    ApplyBatch {
        session: String,
        batch: Batch,
        #[serde(default)]
        wait: bool,
    },
    /// Solve now whatever the policy; with `wait`, answer when it has finished.
    Optimize {
        session: String,
        #[serde(default)]
        wait: bool,
        /// First wait until this producer's batches up to `after_seq` are applied (see
        /// `After`), at most `after_timeout_ms`.
        #[serde(default)]
        after_producer: Option<String>,
        #[serde(default, deserialize_with = "wire_number::optional_u64")]
        after_seq: Option<u64>,
        #[serde(default, deserialize_with = "wire_number::optional_u64")]
        after_timeout_ms: Option<u64>,
    },
    SetAutoOptimize {
        session: String,
        auto_optimize: AutoOptimize,
    },
    /// Declare more user-defined factor types in a running graph session (all or none);
    /// answers the session's info with every declared name.
    DefineFactorTypes {
        session: String,
        factor_types: Vec<crate::factors::expression::FactorTypeDefinition>,
    },
    GetEstimate {
        session: String,
        #[serde(default, deserialize_with = "wire_number::optional_u64")]
        since: Option<u64>,
        #[serde(default, deserialize_with = "wire_number::optional_u64")]
        from: Option<Key>,
        #[serde(default, deserialize_with = "wire_number::optional_u64")]
        to: Option<Key>,
        /// As for `optimize`.
        #[serde(default)]
        after_producer: Option<String>,
        #[serde(default, deserialize_with = "wire_number::optional_u64")]
        after_seq: Option<u64>,
        #[serde(default, deserialize_with = "wire_number::optional_u64")]
        after_timeout_ms: Option<u64>,
        /// `json` (default), or a file: `tum`, `kitti`, `g2o`, `ply` (see `api::export`).
        #[serde(default)]
        format: Option<crate::api::export::EstimateFormat>,
    },
    /// Where a producer's batches stand in a session (exactly-once ingest).
    ProducerStatus {
        session: String,
        producer: String,
    },
    GetStats {
        session: String,
    },
    Cancel {
        session: String,
    },
    /// IMU samples, keyframes, relative poses and priors for a `sliding_window` session.
    Fusion {
        session: String,
        messages: Vec<crate::api::fusion::FusionMessage>,
    },
    /// What the web view draws: positions, initial guesses and pose-to-pose edges.
    GetGraph {
        session: String,
    },
    /// The session's timeline of solves, recent events and rejected inputs (the web view's
    /// history, kept bounded in memory).
    GetHistory {
        session: String,
    },
    /// Marginal covariances of `keys` at the current estimate (and their joint covariance).
    GetMarginals {
        session: String,
        #[serde(deserialize_with = "wire_number::u64_list")]
        keys: Vec<Key>,
        #[serde(default)]
        joint: bool,
    },
}

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

#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct Accepted {
    #[serde(flatten)]
    pub ack: BatchAck,
    /// With `wait`: whether the estimate now reflects this batch (false when no solve was due
    /// under the auto-optimise policy, the solve failed — see `last_error` —, or the wait
    /// timed out).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub solved: Option<bool>,
}

#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
#[serde(untagged)]
pub enum Reply {
    Health(Health),
    Sessions {
        sessions: Vec<SessionInfo>,
    },
    Created(SessionInfo),
    Deleted {
        deleted: String,
    },
    Accepted(Accepted),
    Optimizing {
        session: String,
        sequence: u64,
        /// With `wait`: the session's statistics after the solve.
        #[serde(skip_serializing_if = "Option::is_none")]
        stats: Option<Box<SessionStats>>,
    },
    AutoOptimize {
        session: String,
        auto_optimize: AutoOptimize,
    },
    Estimate(Estimate),
    /// The estimate as a file (`estimate?format=tum|kitti|g2o|ply`): transports serve `body`
    /// as text where they can (HTTP, the zenoh estimate queryable), rpc as this JSON.
    Export(crate::api::export::Export),
    Stats(Box<SessionStats>),
    Cancelled {
        session: String,
        cancelled: bool,
    },
    Fusion(crate::api::fusion::FusionAck),
    Graph(Box<crate::api::wire::Graph>),
    Producer(ProducerStatus),
    Marginals(Box<crate::api::wire::Marginals>),
    History(Box<crate::api::history::SessionHistory>),
}

impl Command {
    /// The estimate read a query string or selector asks for (HTTP, zenoh).
    pub fn get_estimate(session: String, query: EstimateQuery) -> Command {
        let EstimateQuery {
            since,
            from,
            to,
            after_producer,
            after_seq,
            after_timeout_ms,
            format,
        } = query;
        Command::GetEstimate {
            session,
            since,
            from,
            to,
            after_producer,
            after_seq,
            after_timeout_ms,
            format,
        }
    }
}

/// The command a message published on a session's topic `in/<topic>` asks for (zenoh
/// `factord/<session>/in/batch`, the WebSocket batch stream): batches and fusion messages are
/// decoded within `max_items` items, and are never waited for (the answer is an event).
pub fn parse_topic(
    session: &str,
    topic: &str,
    payload: &[u8],
    max_items: usize,
) -> Result<Command, ServiceError> {
    let session = session.to_string();
    match topic {
        "batch" => Ok(Command::ApplyBatch {
            session,
            batch: parse_json_within(payload, max_items)?,
            wait: false,
        }),
        "optimize" => Ok(Command::Optimize {
            session,
            wait: false,
            after_producer: None,
            after_seq: None,
            after_timeout_ms: None,
        }),
        "fusion" => {
            let batch: crate::api::fusion::FusionBatch = parse_json_within(payload, max_items)?;
            Ok(Command::Fusion {
                session,
                messages: batch.messages,
            })
        }
        other => Err(ServiceError::bad_request(
            "unknown_topic",
            "key",
            format!("nothing listens on `in/{other}` (batch, optimize, fusion)"),
        )),
    }
}

/// Decodes an rpc command. A tagged enum hides where inside it a field was wrong, so when the
/// command does not decode, the part that failed is decoded again on its own (a batch, a
/// creation request) to name the field, as HTTP does (`batch.variables[0].kind`). Lists hold
/// at most `max_items` items (413 otherwise, found while decoding); a large command that does
/// not decode is not decoded again, as a JSON tree that can take ten times its size.
pub fn parse_command(bytes: &[u8], max_items: usize) -> Result<Command, ServiceError> {
    /// Commands beyond this size are not re-read to locate their error.
    const LOCATE_AT_MOST: usize = 4 << 20;
    // serde buffers a tagged enum whole before decoding its variant: the two commands that
    // carry many items are decoded as their own structs, streaming, with the item budget.
    match parse_json::<OpOnly>(bytes).map(|o| o.op) {
        Ok(Some(op)) if op == "apply_batch" => {
            let rpc =
                parse_json_within::<ApplyBatchRpc>(bytes, max_items).map_err(with_named_field)?;
            return Ok(Command::ApplyBatch {
                session: rpc.session,
                batch: rpc.batch,
                wait: rpc.wait,
            });
        }
        Ok(Some(op)) if op == "fusion" => {
            let rpc = parse_json_within::<FusionRpc>(bytes, max_items).map_err(with_named_field)?;
            return Ok(Command::Fusion {
                session: rpc.session,
                messages: rpc.messages,
            });
        }
        _ => {}
    }
    let error = match parse_json_within::<Command>(bytes, max_items) {
        Ok(command) => return Ok(command),
        Err(e) if e.kind == super::ErrorKind::TooLarge || bytes.len() > LOCATE_AT_MOST => {
            return Err(e)
        }
        Err(e) => e,
    };
    let Ok(serde_json::Value::Object(mut object)) = serde_json::from_slice(bytes) else {
        return Err(error);
    };
    let located = match object.get("op").and_then(|op| op.as_str()) {
        Some("apply_batch") => object
            .get("batch")
            .and_then(|batch| parse_part::<Batch>(batch, Some("batch"))),
        Some("set_auto_optimize") => object
            .get("auto_optimize")
            .and_then(|policy| parse_part::<AutoOptimize>(policy, Some("auto_optimize"))),
        Some("fusion") => object.get("messages").and_then(|messages| {
            let batch = serde_json::json!({ "messages": messages });
            parse_part::<crate::api::fusion::FusionBatch>(&batch, None)
        }),
        Some("create_session") => {
            object.remove("op");
            parse_part::<CreateSession>(&serde_json::Value::Object(object), None)
        }
        _ => None,
    };
    Err(located
        .filter(|e| e.body.field.is_some())
        .unwrap_or_else(|| with_named_field(error)))
}

/// The `op` of a command, every other field skipped unread.
#[derive(Deserialize)]
struct OpOnly {
    #[serde(default)]
    op: Option<String>,
}

/// [`Command::ApplyBatch`] as its own struct (see [`parse_command`]).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ApplyBatchRpc {
    #[allow(dead_code)]
    op: serde::de::IgnoredAny,
    session: String,
    batch: Batch,
    #[serde(default)]
    wait: bool,
}

/// [`Command::Fusion`] as its own struct (see [`parse_command`]).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FusionRpc {
    #[allow(dead_code)]
    op: serde::de::IgnoredAny,
    session: String,
    #[serde(deserialize_with = "crate::api::wire_list::items")]
    messages: Vec<crate::api::fusion::FusionMessage>,
}

/// Decodes one part of a command on its own, where serde keeps the path: the error, with its
/// field under `prefix` (the part itself when the error has no path).
fn parse_part<T: serde::de::DeserializeOwned>(
    part: &serde_json::Value,
    prefix: Option<&str>,
) -> Option<ServiceError> {
    let mut error = parse_json::<T>(part.to_string().as_bytes()).err()?;
    if let Some(prefix) = prefix {
        error.body.field = Some(match error.body.field.take() {
            Some(f) => format!("{prefix}.{f}"),
            None => prefix.to_string(),
        });
    }
    Some(error)
}

/// serde names a missing or unknown field in its message (`missing field `keys``) even where
/// the path is lost; that name becomes the error's field.
fn with_named_field(mut error: ServiceError) -> ServiceError {
    if error.body.field.is_none() {
        let message = &error.body.message;
        let named = ["missing field `", "unknown field `"]
            .iter()
            .find_map(|prefix| message.split_once(prefix))
            .and_then(|(_, rest)| rest.split_once('`'))
            .map(|(name, _)| name.to_string());
        error.body.field = named;
    }
    error
}
