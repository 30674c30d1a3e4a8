//! What a session runs, decided once when it is created from its kind: a *graph* (batches of
//! variables and factors into a problem that is re-solved incrementally: pose graphs, bundle
//! adjustment) or a *window* (fusion messages into a [`SlidingWindow`]).
//!
//! Every operation that depends on it matches on [`Engine`]; what an engine does not offer is
//! refused with the typed errors below. This is the only file of the session module that names
//! session kinds.
//!
//! An enum rather than a trait with two implementations: there are exactly two engines, the
//! operations need the rest of the session (its lock, journal and event stream) around what
//! the engine holds, and a `match` makes every operation say what it does for each engine,
//! where a trait would spread "not offered" defaults over both implementations.

use std::sync::atomic::AtomicU64;
use std::sync::Mutex;

use crate::api::catalogue::{self, SessionKind};
use crate::api::ServiceError;
use crate::fusion::window::SlidingWindow;
use crate::solver::marginals::Marginals;

// One per session: the size of the larger variant costs nothing worth a box.
#[allow(clippy::large_enum_variant)]
pub(super) enum Engine {
    Graph(Graph),
    Window(Window),
}

/// What a graph session holds besides its state (the problem, the mirror and the solve
/// bookkeeping, behind the session lock).
pub(super) struct Graph {
    /// The dimension the web view draws its graph in.
    pub(super) dimension: u8,
    /// The last factorisation for marginal covariances, with the (sequence, solves) of the
    /// estimate it was taken at.
    pub(super) marginals: Mutex<Option<((u64, u64), Marginals)>>,
    /// What that factorisation holds, read by `memory_bytes` without its lock.
    pub(super) marginals_bytes: AtomicU64,
}

/// A window session's estimator.
pub(super) struct Window {
    /// The window, from the session's `start` message on.
    pub(super) window: Mutex<Option<SlidingWindow>>,
    /// Every keyframe that left the window, as it left (lag-smoothed), oldest first: with the
    /// window's own keyframes, the trajectory a `tum` export serves. Locked after `window`.
    pub(super) smoothed: Mutex<Vec<SmoothedKeyframe>>,
    /// Its batch and solve counters and last summary, for stats. Locked after `window`.
    pub(super) progress: Mutex<super::window_progress::WindowProgress>,
}

/// A keyframe's pose as it left the window (the velocity and biases are not kept: 64 bytes).
#[derive(Clone, Copy, Debug)]
pub(super) struct SmoothedKeyframe {
    pub key: crate::problem::Key,
    pub t: f64,
    pub position: [f64; 3],
    pub rotation_xyzw: [f64; 4],
}

impl Engine {
    pub(super) fn for_kind(kind: &SessionKind) -> Self {
        let graph = |dimension| {
            Engine::Graph(Graph {
                dimension,
                marginals: Mutex::new(None),
                marginals_bytes: AtomicU64::new(0),
            })
        };
        match kind.name {
            catalogue::SLIDING_WINDOW => Engine::Window(Window {
                window: Mutex::new(None),
                smoothed: Mutex::new(Vec::new()),
                progress: Mutex::default(),
            }),
            "pose_graph_2d" => graph(2),
            _ => graph(3),
        }
    }
}

/// A batch of variables and factors sent to a window session.
pub(super) fn batches_refused(session: &str) -> ServiceError {
    ServiceError::bad_request(
        "wrong_kind",
        "session",
        format!(
            "session `{session}` is a sliding window: send fusion messages (POST …/fusion, zenoh in/fusion)"
        ),
    )
}

/// Fusion messages sent to a graph session of kind `kind`.
pub(super) fn fusion_refused(session: &str, kind: &str) -> ServiceError {
    ServiceError::bad_request(
        "wrong_kind",
        "session",
        format!(
            "session `{session}` is of kind {kind}; fusion messages go to {} sessions",
            catalogue::SLIDING_WINDOW
        ),
    )
}

/// Why a window session's first message must be `start` (the window does not exist before).
pub(super) fn start_first() -> String {
    format!(
        "the first message of a {} session must be `start`",
        catalogue::SLIDING_WINDOW
    )
}
