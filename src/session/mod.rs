//! A session: one incrementally growing problem (or, for a sliding window, the window its fusion
//! messages build), its solver options and auto-optimise policy, the estimate clients read, and
//! the events it streams.
//!
//! Concurrency: the problem moves to a pool worker for a solve. Batches that arrive meanwhile are
//! validated against the *mirror* (every accepted variable's kind and wire value), acknowledged
//! with their sequence number, and queued; the worker applies them when it hands the problem back
//! and they are coalesced into the next solve. Reads are always served from the mirror, so they
//! never wait for a solve.
//!
//! The session is one type, [`Session`], whose methods are spread over files by concept; they
//! share its private state. What it runs, a graph of variables and factors or a sliding window
//! fed with fusion messages, is its `Engine`, chosen once at creation.
//!
//! - `mod.rs`: the type, its construction, its lock and who owns it.
//! - `engine.rs`: the two engines, choosing one from the session kind (the only place that
//!   names kinds), and the errors for what an engine does not offer.
//! - `state.rs`: `State`, everything behind that lock, split by who changes it: the problem
//!   (`Model`), the `Mirror`, the `Schedule`, the `SolveResults`, the producers.
//! - `mirror.rs`: [`MirrorEntry`], variables as clients see them, and the estimate read from them.
//! - `apply.rs`: accepting a batch as validate → journal → mirror → schedule (a client's,
//!   acknowledged once durable), and replaying one from the journal (its own path).
//! - `batch.rs`: validating a wire batch into a prepared one.
//! - `producers.rs`: exactly-once ingest (producer ids and sequence numbers, kept acks).
//! - `ordering.rs`: waiting for a producer's batches (`after`) and its progress.
//! - `schedule.rs`: when solves run (auto-optimise policy, `optimize`), waiting for them and
//!   cancelling them.
//! - `schedule_state.rs`: the solve scheduling's state machine (idle, waiting, queued,
//!   solving, lent), every transition in one place.
//! - `solve.rs`: a solve on a pool worker and handing the problem back.
//! - `solve_budget.rs`: what stops a running solve inside an iteration (cancel, delete, time).
//! - `incremental.rs`: re-solving only the region new factors reach.
//! - `bundle.rs`: a bundle adjustment's steps after its solve (lost points triangulated again,
//!   a restart from the client's values when asked or at rest).
//! - `events.rs`: the event channel (publishing, rejections, raw subscriptions).
//! - `history.rs`: the bounded timeline and event log every published event feeds (web view).
//! - `stream.rs`: [`EventStream`], the subscriber every stream reads through: a lag yields a
//!   `lagged` marker and the latest values instead of a silent gap.
//! - `stats.rs`: info, stats and memory accounting.
//! - `inspect.rs`: the drawable graph (of either engine) and marginal covariances (graphs).
//! - `durable.rs`: journal, snapshots and recovery.
//! - `fusion.rs`: applying fusion messages to a window and optimising it at keyframes.

mod apply;
mod background_priority;
pub mod batch;
mod batch_limits;
mod bundle;
mod durable;
mod engine;
mod events;
pub mod factor_types;
pub mod fusion;
mod history;
mod incremental;
mod inspect;
mod mirror;
mod outliers;
mod prepared;
mod producer_order;
mod producers;
mod provisional;
mod relinearize_beside;
mod robots;
mod schedule;
mod schedule_state;
mod solve;
mod solve_budget;
mod state;
mod state_lock;
mod stats;
mod stream;
mod window_marginals;
mod window_progress;

use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex, MutexGuard};

use tokio::sync::{broadcast, watch};

pub use durable::{Durability, Recovery};
use engine::Engine;
pub use events::EventSlot;
pub use mirror::MirrorEntry;
pub use producer_order::Progress;
pub use producers::{check_producer_id, Origin};
use state::State;
pub use stream::EventStream;

use crate::api::catalogue::SessionKind;
use crate::api::wire::AutoOptimize;
use crate::runtime::pool::PoolHandle;
use crate::solver::SolverOptions;

pub struct Session {
    pub name: String,
    pub kind: &'static SessionKind,
    /// Factor types its client declared (at creation or since).
    factor_types: std::sync::RwLock<factor_types::FactorTypes>,
    state: state_lock::StateLock<State>,
    /// Published events in slots the session can take back; `unread` bounds what the events
    /// not yet taken by every subscriber hold (see `events`).
    events: broadcast::Sender<Arc<events::EventSlot>>,
    unread: Mutex<events::UnreadEvents>,
    /// The timeline and recent events, fed by every published event.
    history: Mutex<history::History>,
    /// Highest sequence a finished solve (or a skipped one) reflects; waiters watch it.
    solved: watch::Sender<u64>,
    /// Highest sequence a provisional answer reflects (sessions with a latency budget, see
    /// `provisional`); waiters for an answer watch it beside `solved`.
    answered: watch::Sender<u64>,
    /// Highest sequence accepted: requests waiting for a producer's batches (`after`) watch it.
    accepted: watch::Sender<u64>,
    /// Number of finished solves (successful, failed or interrupted).
    completed: watch::Sender<u64>,
    cancel: AtomicBool,
    /// A graph or a sliding window, by kind.
    engine: Engine,
    /// Where the session is kept on disk, when it is durable.
    durable: Mutex<Option<durable::Durable>>,
    /// Held shared by a journalled batch from its journal write to its acknowledgement, and
    /// taken exclusively by everything that publishes a solve's results (`journal_barrier`):
    /// the fsync runs with the journal unlocked (group commit), so the journal lock no longer
    /// orders an acknowledgement before what a solve publishes of the batch; this does.
    acknowledging: std::sync::RwLock<()>,
    /// Being rebuilt from its journal: writes are refused until it is done.
    recovering: AtomicBool,
    /// Handed to another instance of a fleet: what still reaches it is refused with 503
    /// `session_moving` (the client retries and reaches the new owner), not 404.
    moved: AtomicBool,
    /// Why its files could not be recovered whole, or its journal made durable (set once,
    /// never cleared): it is read-only.
    corruption: std::sync::OnceLock<String>,
    /// The label of the bearer token that created it (HTTP with tokens), else nobody.
    owner: std::sync::OnceLock<Arc<str>>,
    /// The ROS 2 topics it is bound to (set once, at creation or recovery); the transport
    /// layer runs the binding.
    ros2: std::sync::OnceLock<crate::api::ros2::Ros2Binding>,
    /// The latency budget (`max_update_ms`, set once at creation or recovery), read without
    /// the lock when an answer says whether it is exact; its state is `State::latency`.
    max_update_ms: std::sync::OnceLock<u64>,
    /// The provisional answer being computed, and what was asked of it meanwhile.
    provisional_flight: provisional::Flight,
    runtime: tokio::runtime::Handle,
    pool: PoolHandle,
    limits: crate::api::Limits,
}

impl Session {
    pub(crate) fn new(
        name: String,
        kind: &'static SessionKind,
        options: SolverOptions,
        auto: AutoOptimize,
        runtime: tokio::runtime::Handle,
        pool: PoolHandle,
        limits: crate::api::Limits,
    ) -> Arc<Self> {
        Arc::new(Self {
            name,
            kind,
            factor_types: Default::default(),
            state: state_lock::StateLock::new(State::new(kind, options, auto)),
            // At least one slot: a zero capacity is no channel.
            events: broadcast::channel(limits.max_subscriber_lag.max(1)).0,
            unread: Mutex::new(events::UnreadEvents::new(limits.max_subscriber_lag_bytes)),
            history: Mutex::default(),
            solved: watch::channel(0).0,
            answered: watch::channel(0).0,
            accepted: watch::channel(0).0,
            completed: watch::channel(0).0,
            cancel: AtomicBool::new(false),
            engine: Engine::for_kind(kind),
            durable: Mutex::new(None),
            acknowledging: std::sync::RwLock::new(()),
            recovering: AtomicBool::new(false),
            moved: AtomicBool::new(false),
            corruption: std::sync::OnceLock::new(),
            owner: std::sync::OnceLock::new(),
            ros2: std::sync::OnceLock::new(),
            max_update_ms: std::sync::OnceLock::new(),
            provisional_flight: Default::default(),
            runtime,
            pool,
            limits,
        })
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock()
    }

    /// Gives the session to the token labelled `owner` (once, at creation or recovery).
    pub fn set_owner(&self, owner: Arc<str>) {
        let _ = self.owner.set(owner);
    }

    pub fn owner(&self) -> Option<&Arc<str>> {
        self.owner.get()
    }

    /// Binds the session to ROS 2 topics (once, at creation or recovery).
    pub fn set_ros2_binding(&self, binding: crate::api::ros2::Ros2Binding) {
        let _ = self.ros2.set(binding);
    }

    pub fn ros2_binding(&self) -> Option<&crate::api::ros2::Ros2Binding> {
        self.ros2.get()
    }

    /// Whether a caller holding the token labelled `principal` may see this session: its
    /// owner, or anyone when it has none.
    pub fn visible_to(&self, principal: Option<&Arc<str>>) -> bool {
        match self.owner.get() {
            None => true,
            Some(owner) => principal == Some(owner),
        }
    }
}

/// 503 `session_moving`: the session is moving between instances of a fleet; try again in a
/// second.
pub fn moving(name: &str) -> crate::api::ServiceError {
    crate::api::ServiceError::unavailable(
        "session_moving",
        format!("session `{name}` is moving between instances of the fleet; try again shortly"),
        1,
    )
}

/// A write this instance may no longer acknowledge: another instance of the fleet took the
/// session over (this one stopped answering for longer than the fleet's lease, see
/// `journal::takeover`). Not acknowledged is all it says: the new owner may hold the write (a
/// producer's retry is recognised by its sequence). Clients retry, and reach the new owner.
pub fn ownership_lost(name: &str) -> crate::api::ServiceError {
    crate::api::ServiceError::unavailable(
        "ownership_lost",
        format!(
            "session `{name}` was taken over by another instance of the fleet while this one \
             was not answering; this write was not acknowledged: retry it"
        ),
        1,
    )
}

impl Session {
    /// What a request to this session gets once it is gone from here: 404, or 503
    /// `session_moving` when it was handed to another instance.
    fn gone(&self) -> crate::api::ServiceError {
        if self.moved.load(std::sync::atomic::Ordering::SeqCst) {
            moving(&self.name)
        } else {
            crate::api::ServiceError::not_found("session", &self.name)
        }
    }

    /// Hands the session over (a fleet's release): every later write is refused with 503
    /// `session_moving`, waiters wake, a running solve stops.
    pub(crate) fn mark_moved(&self) {
        self.moved.store(true, std::sync::atomic::Ordering::SeqCst);
        self.mark_deleted();
    }
}

/// What unit tests of a session need: one of kind `pose_graph_2d` with manual solving, on a
/// runtime and a one-worker pool of its own (kept alive by the caller).
#[cfg(test)]
pub(crate) fn test_session(
    name: &str,
) -> (
    tokio::runtime::Runtime,
    crate::runtime::pool::WorkerPool,
    std::sync::Arc<Session>,
) {
    let runtime = tokio::runtime::Runtime::new().expect("a test runtime");
    let pool = crate::runtime::pool::WorkerPool::new(1);
    let kind = crate::api::catalogue::session_kind("pose_graph_2d").expect("a built-in kind");
    let session = Session::new(
        name.into(),
        kind,
        (kind.default_options)(),
        crate::api::wire::AutoOptimize::Manual {},
        runtime.handle().clone(),
        pool.handle(),
        crate::api::Limits::default(),
    );
    (runtime, pool, session)
}
