//! A session's recent history, as the web view reads it on load: a timeline of its solves (χ²,
//! solve time, update latency) and the last events of its stream, kept bounded in memory by the
//! session (`GET /v1/sessions/{id}/history`, command `get_history`). A durable session also
//! keeps it in its directory, so it outlives a restart (events from before one come back as
//! they were streamed: [`LoggedData::Restored`]).

use std::sync::Arc;

use serde::{Deserialize, Serialize};

use super::wire::SessionEvent;

/// Most timeline points a session keeps (the oldest go first).
pub const TIMELINE_POINTS: usize = 2000;
/// Most events kept for the log (accepted batches, summaries, errors).
pub const LOGGED_EVENTS: usize = 200;
/// Most rejected inputs and failed solves kept.
pub const REJECTIONS: usize = 100;

#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct SessionHistory {
    pub session: String,
    /// One point per finished solve (graphs) or optimised keyframe (sliding windows), oldest
    /// first, at most [`TIMELINE_POINTS`].
    pub timeline: Vec<TimelinePoint>,
    /// The last events of the session's stream, oldest first: `acks`, `summary` (iteration logs
    /// included) and `errors`, at most [`LOGGED_EVENTS`]. Each is the event as streamed.
    pub events: Vec<LoggedEvent>,
    /// Rejected inputs and failed solves (`errors` events), oldest first, at most
    /// [`REJECTIONS`]: kept longer than the log, which busy streams fill with acks.
    pub rejected: Vec<LoggedEvent>,
    /// Why the last solve failed (or the session is damaged), as in its stats.
    #[schema(required = true)]
    pub last_error: Option<String>,
    /// Timeline points and events dropped for space since the session started here.
    pub dropped: u64,
}

#[derive(Clone, Debug, Serialize, Deserialize, utoipa::ToSchema)]
pub struct TimelinePoint {
    /// When the solve finished (milliseconds since the Unix epoch).
    pub unix_ms: u64,
    /// The solve's number in the session (0 for sliding-window updates).
    pub solve: u64,
    /// The sequence the estimate reflects after it.
    pub sequence: u64,
    /// χ² after the solve (none for sliding-window updates).
    #[schema(required = true)]
    pub chi2: Option<f64>,
    /// Time spent solving.
    pub solve_seconds: f64,
    /// From the acceptance of the oldest batch this solve newly reflects to its end (for a
    /// sliding window, from the keyframe's arrival to its optimised state); none when the solve
    /// reflected no new batch.
    #[schema(required = true)]
    pub latency_seconds: Option<f64>,
    pub iterations: usize,
    pub converged: bool,
}

#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct LoggedEvent {
    /// When it was published (milliseconds since the Unix epoch).
    pub unix_ms: u64,
    /// Its stream name (`acks`, `summary`, `errors`).
    pub event: &'static str,
    /// The event, as the stream sent it.
    #[schema(value_type = SessionEvent)]
    pub data: LoggedData,
}

/// A logged event's content: published by this process, or read back from the session's
/// history file (published before a restart, or by the instance that held the session before).
#[derive(Clone, Debug)]
pub enum LoggedData {
    /// Kept once, shared with the stream's subscribers.
    Live(Arc<SessionEvent>),
    /// As it was streamed then, with its serialised size (counted in the session's memory).
    Restored {
        event: Arc<serde_json::Value>,
        bytes: usize,
    },
}

impl Serialize for LoggedData {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            Self::Live(event) => event.as_ref().serialize(s),
            Self::Restored { event, .. } => event.as_ref().serialize(s),
        }
    }
}
