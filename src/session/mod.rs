//! A session: one incrementally growing problem, its solver options and auto-optimise policy, the
//! estimate clients read, and the events it streams.
//!
//! Concurrency: the problem moves to a pool worker for a solve. Batches that arrive meanwhile are
//! validated against the *mirror* (every accepted variable's kind and wire value), acknowledged
//! with their sequence number, and queued; the worker applies them when it hands the problem back
//! and they are coalesced into the next solve. Reads are always served from the mirror, so they
//! never wait for a solve.
//!
//! The session is one type, [`Session`], whose methods are spread over files by concept; they
//! share its private state:
//!
//! - `mod.rs`: the type, its construction, its lock and who owns it.
//! - `state.rs`: `State`, everything behind that lock, and how a new one starts.
//! - `mirror.rs`: [`MirrorEntry`], variables as clients see them, and the estimate read from them.
//! - `apply.rs`: accepting a batch (limits, validation, journal, mirror, problem or queue).
//! - `schedule.rs`: when solves run (auto-optimise policy, `optimize`), waiting for them and
//!   cancelling them.
//! - `solve.rs`: a solve on a pool worker and handing the problem back.
//! - `incremental.rs`: the engine that re-solves only the region new factors reach.
//! - `events.rs`: the event stream (subscribing, publishing, rejections).
//! - `stats.rs`: info, stats and memory accounting.
//! - `inspect.rs`: the graph and marginal covariances.
//! - `durable.rs`: journal, snapshots and recovery.
//! - `fusion.rs`: sliding-window sessions fed by fusion messages.
//! - `batch.rs`: validating a wire batch into a prepared one.
//! - `catalogue.rs`: session kinds and variable codecs.
//! - `wire.rs`, `wire_list.rs`, `wire_number.rs`: the wire types and their parsing.

mod apply;
pub mod batch;
mod durable;
mod events;
pub mod fusion;
mod incremental;
mod inspect;
mod mirror;
mod schedule;
mod solve;
mod state;
mod stats;

use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex, MutexGuard};

use tokio::sync::{broadcast, watch};

pub use durable::{Durability, Recovery};
pub use mirror::MirrorEntry;
use state::State;

use crate::api::catalogue::SessionKind;
use crate::api::wire::{AutoOptimize, SessionEvent};
use crate::runtime::pool::PoolHandle;
use crate::solver::SolverOptions;

pub struct Session {
    pub name: String,
    pub kind: &'static SessionKind,
    state: Mutex<State>,
    events: broadcast::Sender<Arc<SessionEvent>>,
    /// Highest sequence a finished solve (or a skipped one) reflects; waiters watch it.
    solved: watch::Sender<u64>,
    /// Number of finished solves (successful, failed or interrupted).
    completed: watch::Sender<u64>,
    cancel: AtomicBool,
    /// The window of a `sliding_window` session, from its `start` message on.
    fusion: Mutex<Option<crate::fusion::window::SlidingWindow>>,
    /// The last factorisation for marginal covariances, with the (sequence, solves) of the
    /// estimate it was taken at.
    marginals: Mutex<Option<((u64, u64), crate::solver::marginals::Marginals)>>,
    /// What that factorisation holds, read by `memory_bytes` without its lock.
    marginals_bytes: std::sync::atomic::AtomicU64,
    /// Where the session is kept on disk, when it is durable.
    durable: Mutex<Option<durable::Durable>>,
    /// Being rebuilt from its journal: writes are refused until it is done.
    recovering: AtomicBool,
    /// Why its files could not be recovered whole (set once, never cleared): it is read-only.
    corruption: std::sync::OnceLock<String>,
    /// The label of the bearer token that created it (HTTP with tokens), else nobody.
    owner: std::sync::OnceLock<Arc<str>>,
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
            state: Mutex::new(State::new(kind, options, auto)),
            events: broadcast::channel(4096).0,
            solved: watch::channel(0).0,
            completed: watch::channel(0).0,
            cancel: AtomicBool::new(false),
            fusion: Mutex::new(None),
            marginals: Mutex::new(None),
            marginals_bytes: std::sync::atomic::AtomicU64::new(0),
            durable: Mutex::new(None),
            recovering: AtomicBool::new(false),
            corruption: std::sync::OnceLock::new(),
            owner: std::sync::OnceLock::new(),
            runtime,
            pool,
            limits,
        })
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // A panic while holding the lock would be a bug; the state is still consistent at every
        // await-free step, so keep serving.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Gives the session to the token labelled `owner` (once, at creation or recovery).
    pub fn set_owner(&self, owner: Arc<str>) {
        let _ = self.owner.set(owner);
    }

    pub fn owner(&self) -> Option<&Arc<str>> {
        self.owner.get()
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
