//! The command API every transport speaks: the wire types (requests, replies, events), how bodies
//! are decoded within limits, the [`Command`]s and [`Reply`]s of the one dispatch, the catalogue
//! of session kinds, variable and factor codecs, and the typed error every layer above returns.
//!
//! Layer 6: imports `variables`, `factors`, `problem`, `solver`, `fusion` and `wire_number`;
//! never `journal`, `session`, `service`, `runtime` or `transport`. The one place that knows how
//! an error maps to an HTTP status is [`error::ErrorKind::status`].

pub mod catalogue;
pub mod command;
pub mod decode;
pub mod error;
pub mod export;
pub mod factor_schema;
pub mod fusion;
pub mod given_options;
pub mod history;
pub mod latency;
mod limits;
mod marginals_wire;
pub mod outliers;
pub mod poses_binary;
pub mod robots;
pub mod ros2;
pub mod wire;
pub mod wire_list;

pub use command::{parse_command, replies::*, requests::*, Command, Reply};
pub use decode::{parse_json, parse_json_within, parse_query};
pub use error::{ErrorBody, ErrorKind, ServiceError};
pub use limits::Limits;
