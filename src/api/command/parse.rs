//! How an rpc payload ([`parse_command`]) or a message on a session's topic ([`parse_topic`])
//! becomes a [`Command`], with a refusal that names the field.

use serde::Deserialize;

use super::requests::{ApplyBatch, Fusion, Optimize};
use super::Command;
use crate::api::decode::{parse_json, parse_json_within};
use crate::api::error::ServiceError;
use crate::api::wire::*;

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
        "batch" => Ok(Command::ApplyBatch(ApplyBatch {
            session,
            batch: parse_json_within(payload, max_items)?,
            wait: false,
        })),
        "optimize" => Ok(Command::Optimize(Optimize {
            session,
            wait: false,
            after: Default::default(),
        })),
        "fusion" => {
            let batch: crate::api::fusion::FusionBatch = parse_json_within(payload, max_items)?;
            Ok(Command::Fusion(Fusion {
                session,
                messages: batch.messages,
            }))
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
            return Ok(Command::ApplyBatch(ApplyBatch {
                session: rpc.session,
                batch: rpc.batch,
                wait: rpc.wait,
            }));
        }
        Ok(Some(op)) if op == "fusion" => {
            let rpc = parse_json_within::<FusionRpc>(bytes, max_items).map_err(with_named_field)?;
            return Ok(Command::Fusion(Fusion {
                session: rpc.session,
                messages: rpc.messages,
            }));
        }
        _ => {}
    }
    let error = match parse_json_within::<Command>(bytes, max_items) {
        Ok(command) => return Ok(command),
        Err(e) if e.kind == crate::api::ErrorKind::TooLarge || bytes.len() > LOCATE_AT_MOST => {
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
