//! The service: the session registry, the worker pool, and the one command API that every
//! transport calls. HTTP and zenoh only translate their requests into a [`Command`] and render the
//! [`Reply`] or [`ServiceError`]; no behaviour lives in an adapter.

pub mod caller;
pub mod command;
mod durability;
pub mod error;
pub mod jobs;
pub mod metrics;
pub mod pool;

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, RwLock};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

pub use caller::Caller;
pub use command::{parse_command, Accepted, Command, Health, Reply};
pub use error::{parse_json, parse_json_within, parse_query, ErrorBody, ServiceError};
use jobs::{Job, JobAnswer, JobParams};
use pool::WorkerPool;

use crate::session::catalogue;
use crate::session::wire::*;
use crate::session::Session;

/// Capacity limits.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Limits {
    /// Solver threads (default: the number of cores).
    pub workers: usize,
    pub max_sessions: usize,
    /// Factors a session may have waiting for its running solve before batches get 429.
    pub max_pending_factors: usize,
    /// Batch jobs running or queued at once before new ones get 503.
    pub max_jobs: usize,
    /// How long `wait` requests wait for a solve.
    pub wait_timeout_ms: u64,
    /// Largest batch: variables + factors + removals + fixes + guesses (413 beyond).
    pub max_batch_items: usize,
    /// Variables and live factors one session may hold (422 `session_full` beyond).
    pub max_variables_per_session: usize,
    pub max_factors_per_session: usize,
    /// A session's solve or a batch job stops after this long (its preempted turns added up),
    /// keeping the best estimate it reached; `last_error` (sessions) or the Summary's
    /// `interrupted` termination (jobs) says so.
    pub max_solve_ms: u64,
    /// A batch job whose solve is estimated (from the graph and its symbolic factorisation) to
    /// need more memory than this is refused with 413 `job_too_large` before it starts.
    pub max_job_memory_bytes: u64,
    /// Event-stream subscribers per session (SSE and WebSocket clients; the zenoh publisher
    /// counts as one) before new ones get 429.
    pub max_subscribers: usize,
}

impl Default for Limits {
    fn default() -> Self {
        let cores = std::thread::available_parallelism().map_or(2, |n| n.get());
        Self {
            workers: cores,
            max_sessions: 1024,
            max_pending_factors: 200_000,
            max_jobs: 2 * cores,
            wait_timeout_ms: 120_000,
            max_batch_items: 1_000_000,
            max_variables_per_session: 10_000_000,
            max_factors_per_session: 50_000_000,
            max_solve_ms: 600_000,
            // A sixth of a 24 GB machine: a few such jobs fit at once, with the sessions.
            max_job_memory_bytes: 4 << 30,
            max_subscribers: 64,
        }
    }
}

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
        })
    }

    /// Rebuilds every session found in the state directory, each in the background: it is
    /// listed at once (with `recovering` in its statistics, writes refused with 503) and
    /// optimised when its journal has been replayed. Returns how many there are.
    pub fn recover_sessions(self: &Arc<Self>) -> Result<usize, crate::journal::JournalError> {
        let Some((state_dir, config)) = self.journal.clone() else {
            return Ok(0);
        };
        self.finish_deletions();
        let found = crate::journal::SessionDir::list(&state_dir)?;
        let names_on_disk = crate::journal::SessionDir::names_on_disk(&state_dir)?;
        // Unnamed creations continue after every name on disk, loadable or not.
        for name in &names_on_disk {
            self.reserve_generated_name(name);
        }
        let on_disk = names_on_disk.len();
        let mut count = 0;
        for (name, dir) in found {
            // Only the small identity files are read here; a session whose identity cannot be
            // read is left on disk, unlisted (its name cannot be created again), and the
            // others start.
            let identity = match dir.load_identity() {
                Ok(identity) => identity,
                Err(e) => {
                    tracing::error!(
                        session = %name,
                        "not recovered, its directory is kept for an operator: {e}"
                    );
                    continue;
                }
            };
            let auto_optimize = identity.request.auto_optimize;
            let session = match self.build_session(name.clone(), identity.request) {
                Ok(session) => session,
                Err(e) => {
                    tracing::error!(session = %name, "not recovered: {}", e.body.message);
                    continue;
                }
            };
            session.mark_recovering();
            if let Some(owner) = &identity.owner {
                session.set_owner(owner.as_str().into());
            }
            self.register(name.clone(), Arc::clone(&session));
            count += 1;
            let config = config.clone();
            tokio::task::spawn_blocking(move || {
                let _span = tracing::info_span!("session", session = %name).entered();
                // The snapshot and journal are read here, off start-up: they can be large.
                let outcome = dir
                    .load_state()
                    .and_then(|recovered| Ok((recovered, dir.open_journal(config.fsync)?)))
                    .map_err(|e| e.to_string())
                    .and_then(|(recovered, journal)| {
                        let durability = crate::session::Durability {
                            dir,
                            journal,
                            config,
                        };
                        session.recover(auto_optimize, recovered, durability)
                    });
                match outcome {
                    Ok(r) if r.corruption.is_some() => tracing::error!(
                        entries = r.entries,
                        "journal damaged, session recovered up to the damage and read-only: {}",
                        r.corruption.unwrap_or_default()
                    ),
                    Ok(r) => tracing::info!(
                        entries = r.entries,
                        truncated_bytes = r.truncated_bytes,
                        seconds = r.seconds,
                        "recovered from snapshot {:?} and journal",
                        r.snapshot_sequence
                    ),
                    Err(e) => {
                        tracing::error!("recovery failed, session kept as far as it got: {e}");
                        session.recovery_failed(&e);
                    }
                }
            });
        }
        if config.fsync == crate::journal::Fsync::Interval {
            let service = Arc::downgrade(self);
            let period = Duration::from_millis(config.interval_ms.max(1));
            self.runtime.spawn(async move {
                loop {
                    tokio::time::sleep(period).await;
                    let Some(service) = service.upgrade() else {
                        return;
                    };
                    let sessions = service.sessions();
                    drop(service);
                    let _ = tokio::task::spawn_blocking(move || {
                        for s in sessions {
                            s.sync_journal();
                        }
                    })
                    .await;
                }
            });
        }
        self.count_unloaded(on_disk.saturating_sub(count));
        Ok(count)
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
    /// dropped) and wakes every request waiting for a solve.
    pub fn shutdown(&self, timeout: Duration) {
        self.pool.shutdown(timeout);
        for s in self.sessions() {
            s.release_waiters();
        }
    }

    fn wait_timeout(&self) -> Duration {
        Duration::from_millis(self.limits.wait_timeout_ms)
    }

    /// Runs `command` with every session in reach (in-process callers).
    pub async fn execute(&self, command: Command) -> Result<Reply, ServiceError> {
        self.execute_as(&Caller::Trusted, command).await
    }

    /// Runs `command` for `caller`: the sessions it names are resolved, and authorised, in
    /// [`Self::session_as`] and nowhere else.
    pub async fn execute_as(
        &self,
        caller: &Caller,
        command: Command,
    ) -> Result<Reply, ServiceError> {
        if !matches!(command, Command::Health) {
            self.refuse_when_stopping()?;
        }
        match command {
            Command::Health => Ok(Reply::Health(self.health(caller))),
            Command::ListSessions => Ok(Reply::Sessions {
                sessions: self
                    .sessions()
                    .iter()
                    .filter(|s| caller.may_see(s))
                    .map(|s| s.info())
                    .collect(),
            }),
            Command::CreateSession(request) => self
                .create_session(request, caller.owner_of_new())
                .map(Reply::Created),
            Command::DeleteSession { session } => {
                self.delete_session(caller, &session)?;
                Ok(Reply::Deleted { deleted: session })
            }
            Command::Fusion { session, messages } => {
                let session = self.writable_as(caller, &session)?;
                let batch = crate::session::fusion::FusionBatch { messages };
                // A keyframe's optimisation takes about a millisecond: off the async threads.
                let ack = tokio::task::spawn_blocking(move || session.apply_fusion(batch))
                    .await
                    .map_err(|e| ServiceError::internal(format!("fusion update failed: {e}")))??;
                Ok(Reply::Fusion(ack))
            }
            Command::ApplyBatch {
                session,
                batch,
                wait,
            } => {
                let session = self.writable_as(caller, &session)?;
                let (ack, will_solve) = session.apply_batch(batch)?;
                metrics::count_accepted_batch();
                let solved = if wait && will_solve {
                    let done = session.wait_solved(ack.sequence, self.wait_timeout()).await;
                    Some(done && session.stats().last_error.is_none())
                } else if wait {
                    Some(session.stats().solved_sequence >= ack.sequence)
                } else {
                    None
                };
                Ok(Reply::Accepted(Accepted { ack, solved }))
            }
            Command::Optimize { session, wait } => {
                let session = self.writable_as(caller, &session)?;
                let (sequence, solve) = session.optimize_now()?;
                let stats = if wait {
                    session.wait_solve(solve, self.wait_timeout()).await;
                    Some(Box::new(session.stats()))
                } else {
                    None
                };
                Ok(Reply::Optimizing {
                    session: session.name.clone(),
                    sequence,
                    stats,
                })
            }
            Command::SetAutoOptimize {
                session,
                auto_optimize,
            } => {
                let session = self.writable_as(caller, &session)?;
                session.set_auto_optimize(auto_optimize)?;
                Ok(Reply::AutoOptimize {
                    session: session.name.clone(),
                    auto_optimize,
                })
            }
            Command::GetEstimate {
                session,
                since,
                from,
                to,
            } => Ok(Reply::Estimate(
                self.session_as(caller, &session)?
                    .estimate(&EstimateQuery { since, from, to }),
            )),
            Command::GetStats { session } => Ok(Reply::Stats(Box::new(
                self.session_as(caller, &session)?.stats(),
            ))),
            Command::GetGraph { session } => Ok(Reply::Graph(Box::new(
                self.session_as(caller, &session)?.graph(),
            ))),
            Command::GetMarginals {
                session,
                keys,
                joint,
            } => {
                let session = self.writable_as(caller, &session)?;
                let query = crate::session::wire::MarginalsQuery { keys, joint };
                self.marginals(session, query)
                    .await
                    .map(|m| Reply::Marginals(Box::new(m)))
            }
            Command::Cancel { session } => {
                let session = self.session_as(caller, &session)?;
                Ok(Reply::Cancelled {
                    cancelled: session.cancel(),
                    session: session.name.clone(),
                })
            }
        }
    }

    /// Marginals off the async threads; while a solve holds the problem, asks again after it
    /// (polling: a queued solve may find nothing to do and finish without a trace).
    async fn marginals(
        &self,
        session: Arc<Session>,
        query: crate::session::wire::MarginalsQuery,
    ) -> Result<crate::session::wire::Marginals, ServiceError> {
        let deadline = Instant::now() + self.wait_timeout();
        let query = Arc::new(query);
        loop {
            let (s, q) = (Arc::clone(&session), Arc::clone(&query));
            let answer = tokio::task::spawn_blocking(move || s.marginals(&q))
                .await
                .map_err(|e| ServiceError::internal(format!("marginals failed: {e}")))??;
            if let Some(marginals) = answer {
                return Ok(marginals);
            }
            if Instant::now() >= deadline {
                return Err(ServiceError::unavailable(
                    "solving",
                    format!(
                        "session `{}` is being solved; ask again when the solve finishes",
                        session.name
                    ),
                    1,
                ));
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    }

    /// A message sent to a session without a reply channel (a zenoh put, a WebSocket message):
    /// `kind` is `batch` (a JSON [`Batch`]) or `optimize`. A rejection goes to the session's
    /// event stream, where its sender listens; it is returned only when there is no such session
    /// (and so no stream to put it on).
    pub async fn deliver(
        &self,
        caller: &Caller,
        session: &str,
        kind: &str,
        payload: &[u8],
    ) -> Result<(), ServiceError> {
        let target = self.session_as(caller, session)?;
        let outcome = match kind {
            "batch" => match parse_json_within::<Batch>(payload, self.limits.max_batch_items) {
                Ok(batch) => {
                    let command = Command::ApplyBatch {
                        session: session.into(),
                        batch,
                        wait: false,
                    };
                    self.execute_as(caller, command).await.map(|_| ())
                }
                Err(e) => Err(e),
            },
            "optimize" => {
                let command = Command::Optimize {
                    session: session.into(),
                    wait: false,
                };
                self.execute_as(caller, command).await.map(|_| ())
            }
            "fusion" => match parse_json_within::<crate::session::fusion::FusionBatch>(
                payload,
                self.limits.max_batch_items,
            ) {
                Ok(batch) => {
                    let command = Command::Fusion {
                        session: session.into(),
                        messages: batch.messages,
                    };
                    self.execute_as(caller, command).await.map(|_| ())
                }
                Err(e) => Err(e),
            },
            other => Err(ServiceError::bad_request(
                "unknown_topic",
                "key",
                format!("nothing listens on `in/{other}` (batch, optimize, fusion)"),
            )),
        };
        if let Err(error) = outcome {
            target.report_rejection(error);
        }
        Ok(())
    }

    /// The service's health; `sessions` counts the sessions `caller` may see.
    pub fn health(&self, caller: &Caller) -> Health {
        let pool = self.pool.handle();
        Health {
            status: if pool.is_stopping() { "stopping" } else { "ok" },
            version: env!("CARGO_PKG_VERSION"),
            workers: self.pool.workers,
            busy_workers: pool.busy(),
            queued: pool.waiting(),
            sessions: match caller {
                Caller::Trusted => self
                    .sessions
                    .read()
                    .unwrap_or_else(|p| p.into_inner())
                    .len(),
                _ => self.sessions().iter().filter(|s| caller.may_see(s)).count(),
            },
            session_kinds: catalogue::SESSION_KINDS.iter().map(|k| k.name).collect(),
            uptime_seconds: self.started.elapsed().as_secs_f64(),
        }
    }

    /// Creates a session owned by the token labelled `owner` (see `transport::http::auth`).
    pub fn create_session(
        &self,
        request: CreateSession,
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
            None => format!("s{}", self.next_id.fetch_add(1, Ordering::SeqCst)),
        };
        let session = self.build_session(name.clone(), request.clone())?;
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
            let info = session.info();
            let record = CreateSession {
                session: Some(name.clone()),
                kind: info.kind,
                options: Some(info.options),
                auto_optimize: info.auto_optimize,
            };
            if let Some(durability) = self.create_files(&name, &record, owner.as_deref())? {
                session.attach(durability);
            }
        }
        self.notify_observers(&session);
        sessions.insert(name, Arc::clone(&session));
        Ok(session.info())
    }

    /// A validated, empty session (not yet listed).
    fn build_session(
        &self,
        name: String,
        request: CreateSession,
    ) -> Result<Arc<Session>, ServiceError> {
        let kind = catalogue::session_kind(&request.kind).ok_or_else(|| {
            let known: Vec<_> = catalogue::SESSION_KINDS.iter().map(|k| k.name).collect();
            ServiceError::bad_request(
                "unknown_kind",
                "kind",
                format!("unknown session kind `{}` (known: {known:?})", request.kind),
            )
        })?;
        let options = request.options.unwrap_or_else(kind.default_options);
        options.validate().map_err(|(field, m)| {
            ServiceError::bad_request("invalid_value", format!("options.{field}"), m)
        })?;
        let session = Session::new(
            name,
            kind,
            options,
            request.auto_optimize,
            self.runtime.clone(),
            self.pool.handle(),
            self.limits.clone(),
        );
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

    /// Unnamed creations (`s<n>`) are numbered after `name` when it is one of theirs.
    fn reserve_generated_name(&self, name: &str) {
        if let Some(n) = name.strip_prefix('s').and_then(|n| n.parse::<u64>().ok()) {
            self.next_id
                .fetch_max(n.saturating_add(1), Ordering::SeqCst);
        }
    }

    /// Lists a recovered session.
    fn register(&self, name: String, session: Arc<Session>) {
        self.notify_observers(&session);
        self.sessions
            .write()
            .unwrap_or_else(|p| p.into_inner())
            .insert(name, session);
    }

    /// Runs a batch job on the pool; 503 when `max_jobs` are already in flight.
    pub async fn run_job(
        &self,
        text: String,
        params: JobParams,
    ) -> Result<JobAnswer, ServiceError> {
        let job = Job::new(
            text,
            params,
            Duration::from_millis(self.limits.max_solve_ms),
            self.limits.max_job_memory_bytes,
        )?;
        let previous = self.jobs_in_flight.fetch_add(1, Ordering::SeqCst);
        let _slot = JobSlot(&self.jobs_in_flight);
        if previous >= self.limits.max_jobs {
            return Err(ServiceError::unavailable(
                "too_many_jobs",
                format!(
                    "{} batch jobs are already running or queued",
                    self.limits.max_jobs
                ),
                1,
            ));
        }
        let (tx, rx) = tokio::sync::oneshot::channel();
        if !job.submit(&self.pool.handle(), tx) {
            return Err(ServiceError::unavailable(
                "shutting_down",
                "the service is shutting down",
                5,
            ));
        }
        rx.await.map_err(|_| {
            ServiceError::unavailable("shutting_down", "the job was dropped at shutdown", 5)
        })?
    }
}

struct JobSlot<'a>(&'a AtomicUsize);

impl Drop for JobSlot<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::SeqCst);
    }
}
