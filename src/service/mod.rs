//! The service: the session registry, callers and authorisation, recovery, and the dispatch of
//! the one command API that every transport calls. HTTP and zenoh only translate their requests
//! into a [`Command`] and render the [`Reply`] or [`ServiceError`]; no behaviour lives in an
//! adapter.
//!
//! Layer 9: imports `session` and everything below; never `transport` or `server`.

pub mod caller;
pub mod commands;
mod delivery;
mod durability;
pub mod fleet;
mod fleet_heartbeat;
pub mod fleet_key;
mod fleet_lock;
mod fleet_moves;
mod gauges;
pub mod jobs;
pub mod placement;
mod recovery;

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, RwLock};
use std::time::{Duration, Instant};

pub use crate::api::Limits;
pub use crate::api::{parse_command, Accepted, Command, Health, Reply};
pub use crate::api::{parse_json, parse_json_within, parse_query, ErrorBody, ServiceError};
use crate::runtime::pool::WorkerPool;
pub use caller::Caller;
pub use commands::Recording;
pub use delivery::Delivery;

use crate::api::{catalogue, wire::*};
use crate::session::factor_types::{FactorTypes, TypeCompiler};
use crate::session::Session;

/// Called for every new session before its creation is acknowledged, so an adapter can follow
/// its events from the first one.
pub type SessionObserver = Box<dyn Fn(&Arc<Session>) + Send + Sync>;

pub struct Service {
    sessions: RwLock<HashMap<String, Arc<Session>>>,
    pool: WorkerPool,
    limits: Limits,
    runtime: tokio::runtime::Handle,
    observers: RwLock<Vec<SessionObserver>>,
    next_id: AtomicU64,
    jobs_in_flight: AtomicUsize,
    started: Instant,
    /// Where durable sessions live, and how.
    journal: Option<(std::path::PathBuf, crate::journal::JournalConfig)>,
    /// Session directories found at start that could not be loaded (see `durability`).
    unloaded_on_disk: AtomicUsize,
    /// This instance's view of its fleet (`fleet.rs`), when it is in one.
    fleet: std::sync::OnceLock<Arc<fleet::Fleet>>,
    /// Factor types from the server's configuration, compiled at start.
    server_factor_types: std::sync::OnceLock<Vec<Arc<crate::factors::expression::ExpressionType>>>,
    /// Where every session's factor types are compiled, shared and bounded.
    type_compiler: TypeCompiler,
    /// Sessions rebuilt at once in the background (one per worker: see `recovery.rs`).
    recovery_slots: Arc<tokio::sync::Semaphore>,
}

/// Runs `work` on a blocking thread (compiling, optimising: milliseconds the async threads
/// must not spend); a panic there is an internal error naming `what`.
pub(crate) async fn off_async<T: Send + 'static>(
    what: &str,
    work: impl FnOnce() -> Result<T, ServiceError> + Send + 'static,
) -> Result<T, ServiceError> {
    tokio::task::spawn_blocking(work)
        .await
        .map_err(|e| ServiceError::internal(format!("{what} failed: {e}")))?
}

/// Session names are zenoh key chunks and URL path segments.
fn valid_session_name(name: &str) -> bool {
    (1..=64).contains(&name.len())
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
}

impl Service {
    /// Must be called inside a tokio runtime (timers of `every_ms` sessions run on it).
    /// Sessions live in memory only.
    pub fn new(limits: Limits) -> Arc<Self> {
        Self::with_journal(limits, None)
    }

    /// Sessions are journalled under `state_dir` (when `journal.enabled`).
    pub fn with_journal(
        limits: Limits,
        journal: Option<(std::path::PathBuf, crate::journal::JournalConfig)>,
    ) -> Arc<Self> {
        let journal = journal.filter(|(_, config)| config.enabled);
        let workers = limits.workers.max(1);
        Arc::new(Self {
            type_compiler: TypeCompiler::new(&limits),
            recovery_slots: Arc::new(tokio::sync::Semaphore::new(workers)),
            sessions: RwLock::new(HashMap::new()),
            pool: WorkerPool::new(workers),
            limits,
            runtime: tokio::runtime::Handle::current(),
            observers: RwLock::new(Vec::new()),
            next_id: AtomicU64::new(1),
            jobs_in_flight: AtomicUsize::new(0),
            started: Instant::now(),
            journal,
            unloaded_on_disk: AtomicUsize::new(0),
            fleet: std::sync::OnceLock::new(),
            server_factor_types: std::sync::OnceLock::new(),
        })
    }

    /// Compiles the configuration's factor types (once, at start); a refusal names the field.
    pub fn set_server_factor_types(
        &self,
        definitions: &[crate::factors::expression::FactorTypeDefinition],
    ) -> Result<(), String> {
        let compiled = FactorTypes::compile_server_wide(self.type_compiler.clone(), definitions)
            .map_err(|e| {
                let field = e.body.field.unwrap_or_default();
                format!("{field}: {}", e.body.message)
            })?;
        if !compiled.is_empty() {
            let names: Vec<&str> = compiled.iter().map(|t| t.name()).collect();
            tracing::info!("factor types for every new session: {names:?}");
        }
        let _ = self.server_factor_types.set(compiled);
        Ok(())
    }

    fn refuse_when_stopping(&self) -> Result<(), ServiceError> {
        if self.pool.handle().is_stopping() {
            return Err(ServiceError::unavailable(
                "shutting_down",
                "the service is shutting down",
                5,
            ));
        }
        Ok(())
    }

    /// A session that takes writes, as `caller` sees it: 503 while it is being rebuilt from
    /// its journal.
    fn writable_as(&self, caller: &Caller, name: &str) -> Result<Arc<Session>, ServiceError> {
        let session = self.session_as(caller, name)?;
        if session.is_recovering() {
            return Err(ServiceError::unavailable(
                "recovering",
                format!("session `{name}` is being rebuilt from its journal; try again shortly"),
                1,
            ));
        }
        durability::refuse_if_corrupt(&session)?;
        Ok(session)
    }

    pub fn limits(&self) -> &Limits {
        &self.limits
    }

    /// Registers `observer` and calls it for every existing session.
    pub fn observe_sessions(&self, observer: SessionObserver) {
        for s in self.sessions() {
            observer(&s);
        }
        self.observers
            .write()
            .unwrap_or_else(|p| p.into_inner())
            .push(observer);
    }

    /// A receiver of the events of session `name` for `caller` (SSE, WebSocket): the same
    /// visibility as [`Self::session_as`], within the session's subscriber limit. Like batch
    /// jobs, not a [`Command`]: its answer is a stream, not one reply (docs/ARCHITECTURE.md).
    pub fn subscribe_as(
        &self,
        caller: &Caller,
        name: &str,
    ) -> Result<crate::session::EventStream, ServiceError> {
        self.session_as(caller, name)?.stream_limited()
    }

    /// The session named `name` if it exists for `caller`; the same 404 as for a session that
    /// was never created otherwise. Every command resolves its session here.
    pub fn session_as(&self, caller: &Caller, name: &str) -> Result<Arc<Session>, ServiceError> {
        self.session(name)
            .ok()
            .filter(|session| caller.may_see(session))
            .ok_or_else(|| ServiceError::not_found("session", name))
    }

    /// The session named `name`, whoever owns it (in-process use; transports use
    /// [`Self::session_as`]).
    pub fn session(&self, name: &str) -> Result<Arc<Session>, ServiceError> {
        self.sessions
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .get(name)
            .cloned()
            .ok_or_else(|| ServiceError::not_found("session", name))
    }

    pub fn sessions(&self) -> Vec<Arc<Session>> {
        let mut all: Vec<_> = self
            .sessions
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .values()
            .cloned()
            .collect();
        all.sort_by(|a, b| a.name.cmp(&b.name));
        all
    }

    /// Stops the pool (running solves stop after their current iteration, queued work is
    /// dropped), wakes every request waiting for a solve and writes the sessions' histories.
    pub fn shutdown(&self, timeout: Duration) {
        self.pool.shutdown(timeout);
        for s in self.sessions() {
            s.release_waiters();
            s.persist_history();
        }
    }

    fn wait_timeout(&self) -> Duration {
        Duration::from_millis(self.limits.wait_timeout_ms)
    }

    /// Registers a new session owned by the token labelled `owner` (see `transport::http::auth`);
    /// `factor_types`: the request's already compiled, else they are compiled here.
    pub fn register_session(
        &self,
        request: CreateSession,
        factor_types: Option<FactorTypes>,
        owner: Option<Arc<str>>,
    ) -> Result<SessionInfo, ServiceError> {
        self.refuse_when_stopping()?;
        let name = match &request.session {
            Some(name) if valid_session_name(name) => name.clone(),
            Some(name) => {
                return Err(ServiceError::bad_request(
                    "invalid_session_name",
                    "session",
                    format!("`{name}` is not 1-64 characters of [A-Za-z0-9_-]"),
                ))
            }
            None => self.generated_name(),
        };
        let session = self.build_session(name.clone(), request.clone(), factor_types)?;
        if let Some(owner) = &owner {
            session.set_owner(Arc::clone(owner));
        }
        // Held across the directory's creation so two creations of one name cannot race.
        let mut sessions = self.sessions.write().unwrap_or_else(|p| p.into_inner());
        if sessions.contains_key(&name) {
            return Err(ServiceError::conflict(
                "session_exists",
                format!("session `{name}` already exists"),
            ));
        }
        // Directories on disk that were not loaded are never overwritten, and count.
        let unloaded = self.unloaded_on_disk(&name)?;
        if sessions.len() + unloaded >= self.limits.max_sessions {
            return Err(ServiceError::unavailable(
                "too_many_sessions",
                format!(
                    "the service holds its maximum of {} sessions{}",
                    self.limits.max_sessions,
                    match unloaded {
                        0 => String::new(),
                        n => format!(" ({n} of them on disk but not loaded)"),
                    }
                ),
                10,
            ));
        }
        if self.journal.is_some() {
            // What recovery needs to build it again: the resolved name, options and policy.
            let record = session.creation_record();
            if let Some(durability) = self.create_files(&name, &record, owner.as_deref())? {
                session.attach(durability);
            }
        }
        self.notify_observers(&session);
        sessions.insert(name, Arc::clone(&session));
        let mut info = session.info();
        info.instance = self.owning_instance();
        Ok(info)
    }

    /// A name for an unnamed creation: the next `s<n>` that no session holds, listed or on disk
    /// (a client may have named one `s1`).
    fn generated_name(&self) -> String {
        let sessions = self.sessions.read().unwrap_or_else(|p| p.into_inner());
        loop {
            let name = format!("s{}", self.next_id.fetch_add(1, Ordering::SeqCst));
            if !sessions.contains_key(&name) && !self.directory_on_disk(&name) {
                return name;
            }
        }
    }

    /// A validated, empty session (not yet listed).
    fn build_session(
        &self,
        name: String,
        request: CreateSession,
        factor_types: Option<FactorTypes>,
    ) -> Result<Arc<Session>, ServiceError> {
        let kind = catalogue::session_kind(&request.kind).ok_or_else(|| {
            let known: Vec<_> = catalogue::SESSION_KINDS.iter().map(|k| k.name).collect();
            ServiceError::bad_request(
                "unknown_kind",
                "kind",
                format!("unknown session kind `{}` (known: {known:?})", request.kind),
            )
        })?;
        let defaults = (kind.default_options)();
        let options = match &request.options {
            Some(given) => given.over(defaults),
            None => defaults,
        };
        options.validate().map_err(|(field, m)| {
            ServiceError::bad_request("invalid_value", format!("options.{field}"), m)
        })?;
        let factor_types = match factor_types {
            Some(compiled) => compiled,
            None => {
                FactorTypes::recovered(self.type_compiler.clone(), kind, &request.factor_types)?
            }
        };
        let session = Session::new(
            name,
            kind,
            options,
            request.auto_optimize,
            self.runtime.clone(),
            self.pool.handle(),
            self.limits.clone(),
        );
        session.set_factor_types(factor_types);
        if let Some(binding) = request.ros2 {
            binding.validate()?;
            binding.check_kind(kind.name)?;
            if binding.robots.is_some() && request.robots.is_none() {
                return Err(ServiceError::bad_request(
                    "invalid_value",
                    "ros2.robots",
                    "a node per robot needs a session with `robots`",
                ));
            }
            session.set_ros2_binding(*binding);
        }
        if let Some(robots) = request.robots {
            session.set_robots(robots)?;
        }
        session.set_outlier_policy(request.outliers)?;
        if let Some(max_update_ms) = request.max_update_ms {
            session.set_latency_budget(max_update_ms)?;
        }
        session
            .set_auto_optimize(request.auto_optimize)
            .map_err(|mut e| {
                e.body.field = e.body.field.map(|f| format!("auto_optimize.{f}"));
                e
            })?;
        Ok(session)
    }

    fn notify_observers(&self, session: &Arc<Session>) {
        for observe in self
            .observers
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .iter()
        {
            observe(session);
        }
    }
}
