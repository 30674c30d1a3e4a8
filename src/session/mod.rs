//! A session: one incrementally growing problem, its solver options and auto-optimise policy, the
//! estimate clients read, and the events it streams.
//!
//! Concurrency: the problem moves to a pool worker for a solve. Batches that arrive meanwhile are
//! validated against the *mirror* (every accepted variable's kind and wire value), acknowledged
//! with their sequence number, and queued; the worker applies them when it hands the problem back
//! and they are coalesced into the next solve. Reads are always served from the mirror, so they
//! never wait for a solve.

pub mod batch;
pub mod catalogue;
mod durable;
pub mod fusion;
mod incremental;
mod inspect;
mod solve;
pub mod wire;
pub mod wire_list;
pub mod wire_number;

use std::collections::{BTreeMap, HashSet, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};

pub use durable::{Durability, Recovery};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use tokio::sync::{broadcast, watch};

use crate::problem::{Key, Problem, Variable};
use crate::service::pool::PoolHandle;
use crate::service::ServiceError;
use crate::solver::{self, SolverOptions};
use batch::{PreparedBatch, SessionView};
use catalogue::SessionKind;
use incremental::Engine;
use wire::*;

/// A variable as clients see it.
#[derive(Clone, Debug)]
pub struct MirrorEntry {
    pub kind: &'static str,
    pub value: Vec<f64>,
    pub changed: u64,
    pub fixed: bool,
    /// Position of the value the client last sent (the web view's initial guess).
    pub initial: [f64; 3],
}

impl MirrorEntry {
    pub fn decode(&self) -> Box<dyn Variable> {
        let codec =
            catalogue::variable_codec(self.kind).expect("mirror kinds come from the catalogue");
        (codec.decode)(&self.value).expect("mirror values were encoded by the codec")
    }
}

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
    limits: crate::service::Limits,
}

struct State {
    options: SolverOptions,
    auto: AutoOptimize,
    /// `None` while a worker has it (with `index`).
    problem: Option<Problem>,
    index: Option<Engine>,
    /// Variables (dense indices) touched by factors added since the last solve.
    seeds: Vec<usize>,
    /// Since the last solve, something other than additions changed (removals, fixes, guesses):
    /// the next solve is of the whole problem.
    structural: bool,
    /// What region re-solves left unsolved at their boundaries (see `incremental`).
    region_debt: f64,
    /// Variables the last full solve fixed to remove the gauge freedom.
    gauge: Vec<Key>,
    /// Id of each factor of the problem, parallel to `problem.factors()`.
    factor_ids: Vec<FactorId>,
    mirror: BTreeMap<Key, MirrorEntry>,
    live_factors: HashSet<FactorId>,
    /// Live factors between two pose-shaped variables (what the web view draws as edges).
    edges: BTreeMap<FactorId, [Key; 2]>,
    next_factor_id: FactorId,
    sequence: u64,
    solved_sequence: u64,
    pending: VecDeque<(u64, PreparedBatch, Vec<FactorId>)>,
    pending_factors: usize,
    factors_since_solve: usize,
    /// Changed since the last solve in a way a solve could improve.
    dirty: bool,
    /// Queued on or running in the pool.
    scheduled: bool,
    /// A solve was asked for (`optimize`): it runs whatever the policy.
    forced: bool,
    solving: bool,
    timer_armed: bool,
    deleted: bool,
    solves: u64,
    skipped_solves: u64,
    chi2: Option<f64>,
    converged: bool,
    last_error: Option<String>,
    last_summary: Option<solver::Summary>,
    /// The problem's size when it was last here (it is on a worker during solves).
    problem_bytes: usize,
    /// Time the current solve spent in earlier (preempted) turns.
    solve_carried: Duration,
}

/// Estimated bytes of a problem: variables (boxed, with their key index) and factors (boxed,
/// with keys, square-root information and label).
fn problem_bytes(problem: &Problem) -> usize {
    use std::mem::size_of;
    let values = problem.values.len() * (size_of::<Box<dyn Variable>>() + 128);
    let factors: usize = problem
        .factors()
        .iter()
        .map(|f| {
            let r = f.factor.residual_dim();
            size_of::<crate::factors::FactorEntry>()
                + 96
                + 8 * (r * r + f.variables().len())
                + f.label.len()
        })
        .sum();
    values + factors
}

impl Session {
    pub(crate) fn new(
        name: String,
        kind: &'static SessionKind,
        options: SolverOptions,
        auto: AutoOptimize,
        runtime: tokio::runtime::Handle,
        pool: PoolHandle,
        limits: crate::service::Limits,
    ) -> Arc<Self> {
        Arc::new(Self {
            name,
            kind,
            state: Mutex::new(State {
                options,
                auto,
                problem: Some(Problem::with_gauge(kind.gauge).eliminating(kind.eliminate)),
                index: Some(Engine::default()),
                seeds: Vec::new(),
                structural: true,
                region_debt: 0.0,
                gauge: Vec::new(),
                factor_ids: Vec::new(),
                mirror: BTreeMap::new(),
                live_factors: HashSet::new(),
                edges: BTreeMap::new(),
                next_factor_id: 0,
                sequence: 0,
                solved_sequence: 0,
                pending: VecDeque::new(),
                pending_factors: 0,
                factors_since_solve: 0,
                dirty: false,
                scheduled: false,
                forced: false,
                solving: false,
                timer_armed: false,
                deleted: false,
                solves: 0,
                skipped_solves: 0,
                chi2: None,
                converged: true,
                last_error: None,
                last_summary: None,
                problem_bytes: 0,
                solve_carried: Duration::ZERO,
            }),
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

    pub fn subscribe(&self) -> broadcast::Receiver<Arc<SessionEvent>> {
        self.events.subscribe()
    }

    /// Publishes a rejection of something sent to this session without a reply channel (a
    /// zenoh put), so subscribers of its stream see it.
    pub fn report_rejection(&self, error: ServiceError) {
        crate::service::metrics::count_rejection(&error.body);
        self.emit(SessionEvent::Error {
            session: self.name.clone(),
            sequence: None,
            error: error.body,
        });
    }

    fn emit(&self, event: SessionEvent) {
        // No subscribers is fine.
        let _ = self.events.send(Arc::new(event));
    }

    pub fn info(&self) -> SessionInfo {
        let st = self.lock();
        SessionInfo {
            session: self.name.clone(),
            kind: self.kind.name.into(),
            options: st.options.clone(),
            auto_optimize: st.auto,
        }
    }

    /// Validates and accepts a batch, journals it (durable sessions) and only then acknowledges
    /// it; returns the acknowledgement and whether a solve reflecting it is scheduled (so a
    /// caller may wait for it).
    pub fn apply_batch(self: &Arc<Self>, batch: Batch) -> Result<(BatchAck, bool), ServiceError> {
        self.accept_batch(batch, None, true)
    }

    /// `ids`: the factor ids to give the batch's factors (a snapshot's), else the next ones.
    /// `journal`: append it to the journal (not when it is being replayed from there).
    fn accept_batch(
        self: &Arc<Self>,
        batch: Batch,
        ids: Option<Vec<FactorId>>,
        journal: bool,
    ) -> Result<(BatchAck, bool), ServiceError> {
        if self.kind.name == catalogue::SLIDING_WINDOW {
            return Err(ServiceError::bad_request(
                "wrong_kind",
                "session",
                format!(
                    "session `{}` is a sliding window: send fusion messages (POST …/fusion, zenoh in/fusion)",
                    self.name
                ),
            ));
        }
        let mut st = self.lock();
        if st.deleted {
            return Err(ServiceError::not_found("session", &self.name));
        }
        // Limits hold for what clients send; a journal replay restores what was accepted.
        if journal {
            self.check_batch_size(&batch)?;
        }
        let mut durable = self.durable.lock().unwrap_or_else(|p| p.into_inner());
        let wire_copy = durable.is_some().then(|| batch.clone());
        let prepared = batch::prepare(
            batch,
            &SessionView {
                kind: self.kind,
                mirror: &st.mirror,
                live_factors: &st.live_factors,
            },
        )?;
        if st.problem.is_none()
            && st.pending_factors + prepared.factor_count() > self.limits.max_pending_factors
        {
            return Err(ServiceError::too_many(
                format!(
                    "session `{}` has {} factors waiting for the running solve; {} more would exceed the limit of {}",
                    self.name,
                    st.pending_factors,
                    prepared.factor_count(),
                    self.limits.max_pending_factors
                ),
                1,
            ));
        }
        if journal {
            self.check_session_size(&st, &prepared)?;
        }
        let sequence = st.sequence + 1;
        let wire_copy = match (durable.as_mut(), wire_copy, journal) {
            (Some(d), Some(copy), true) => {
                Some(d.append_batch(&self.name, sequence, copy, &prepared)?)
            }
            (_, copy, _) => copy,
        };
        st.sequence = sequence;
        let factor_ids: Vec<FactorId> = match ids {
            Some(ids) => ids,
            None => (0..prepared.factors.len() as u64)
                .map(|k| st.next_factor_id + k)
                .collect(),
        };
        st.next_factor_id = factor_ids
            .iter()
            .map(|id| id + 1)
            .fold(st.next_factor_id, u64::max);
        if let (Some(d), Some(copy)) = (durable.as_mut(), wire_copy) {
            d.track_factors(copy.factors, &factor_ids, &prepared.remove);
        }
        // Mirror first: later batches validate against it even while this one waits.
        let mut new_values = Vec::new();
        for (key, v, fixed) in &prepared.variables {
            let value = catalogue::encode_variable(v.as_ref());
            let entry = MirrorEntry {
                kind: v.kind(),
                initial: inspect::position(v.kind(), &value),
                value,
                changed: sequence,
                fixed: *fixed,
            };
            new_values.push(value_of(*key, &entry));
            st.mirror.insert(*key, entry);
        }
        for (key, v) in &prepared.guesses {
            let value = catalogue::encode_variable(v.as_ref());
            let entry = st.mirror.get_mut(key).expect("validated");
            entry.initial = inspect::position(entry.kind, &value);
            entry.value = value;
            entry.changed = sequence;
            new_values.push(value_of(*key, entry));
        }
        for &(key, fixed) in &prepared.fix {
            st.mirror.get_mut(&key).expect("validated").fixed = fixed;
        }
        st.live_factors.extend(factor_ids.iter().copied());
        for (f, &id) in prepared.factors.iter().zip(&factor_ids) {
            if let Some(edge) = inspect::edge(&st.mirror, f.factor.keys()) {
                st.edges.insert(id, edge);
            }
        }
        for id in &prepared.remove {
            st.live_factors.remove(id);
            st.edges.remove(id);
        }
        let predicted = prepared.predicted.clone();
        if st.problem.is_some() {
            self.apply_prepared(&mut st, sequence, prepared, factor_ids.clone());
        } else {
            st.pending_factors += prepared.factor_count();
            st.pending
                .push_back((sequence, prepared, factor_ids.clone()));
            st.dirty = true;
        }
        let ack = BatchAck {
            session: self.name.clone(),
            sequence,
            factor_ids,
            predicted,
            reflected: st.solved_sequence >= sequence,
        };
        self.emit(SessionEvent::Ack(ack.clone()));
        if !new_values.is_empty() {
            self.emit(SessionEvent::Estimate(Estimate {
                session: self.name.clone(),
                sequence,
                variables: new_values,
            }));
        }
        self.maybe_schedule(&mut st);
        let will_solve = st.solved_sequence < sequence && (st.scheduled || st.timer_armed);
        if let (Some(d), true) = (durable.as_mut(), journal) {
            d.maybe_snapshot(&self.name, self.kind.name, &st);
        }
        Ok((ack, will_solve))
    }

    fn check_batch_size(&self, batch: &Batch) -> Result<(), ServiceError> {
        let items = batch.variables.len()
            + batch.factors.len()
            + batch.remove_factors.len()
            + batch.fix.len()
            + batch.unfix.len()
            + batch.guesses.len();
        if items > self.limits.max_batch_items {
            return Err(ServiceError::new(
                413,
                "batch_too_large",
                format!(
                    "the batch has {items} items (variables, factors, removals, fixes, guesses); the limit is {} (limits.max_batch_items): split it",
                    self.limits.max_batch_items
                ),
            )
            .at("batch"));
        }
        Ok(())
    }

    fn check_session_size(&self, st: &State, prepared: &PreparedBatch) -> Result<(), ServiceError> {
        let variables = st.mirror.len() + prepared.variables.len();
        if variables > self.limits.max_variables_per_session {
            return Err(ServiceError::invalid(
                "session_full",
                "variables",
                format!(
                    "session `{}` would hold {variables} variables; the limit is {} (limits.max_variables_per_session)",
                    self.name, self.limits.max_variables_per_session
                ),
            ));
        }
        let factors =
            (st.live_factors.len() + prepared.factors.len()).saturating_sub(prepared.remove.len());
        if factors > self.limits.max_factors_per_session {
            return Err(ServiceError::invalid(
                "session_full",
                "factors",
                format!(
                    "session `{}` would hold {factors} factors; the limit is {} (limits.max_factors_per_session)",
                    self.name, self.limits.max_factors_per_session
                ),
            ));
        }
        Ok(())
    }

    /// Event-stream subscribers now (the zenoh publisher included).
    pub fn subscribers(&self) -> usize {
        self.events.receiver_count()
    }

    /// A new event-stream subscriber, or 429 at `limits.max_subscribers`.
    pub fn subscribe_limited(
        &self,
    ) -> Result<broadcast::Receiver<Arc<SessionEvent>>, ServiceError> {
        if self.subscribers() >= self.limits.max_subscribers {
            let mut e = ServiceError::new(
                429,
                "too_many_subscribers",
                format!(
                    "session `{}` has {} event subscribers, the limit (limits.max_subscribers)",
                    self.name, self.limits.max_subscribers
                ),
            )
            .at("session");
            e.body.retry_after = Some(5);
            return Err(e);
        }
        Ok(self.subscribe())
    }

    /// Applies a validated batch to the problem (present in `st`).
    fn apply_prepared(
        &self,
        st: &mut State,
        sequence: u64,
        prepared: PreparedBatch,
        factor_ids: Vec<FactorId>,
    ) {
        let State {
            problem,
            index,
            factor_ids: ids,
            seeds,
            ..
        } = st;
        let problem = problem.as_mut().expect("caller checked");
        let index = index.as_mut().expect("kept with the problem");
        let first_new_factor = problem.factors().len();
        let mut structural = !prepared.remove.is_empty() || !prepared.fix.is_empty();
        let adds_variables = !prepared.variables.is_empty();
        for (key, v, fixed) in prepared.variables {
            problem.add_variable(key, v).expect("validated");
            if fixed {
                problem.set_fixed(key, true).expect("validated");
            }
        }
        let added = prepared.factors.len();
        for (f, id) in prepared.factors.into_iter().zip(factor_ids) {
            problem
                .add_checked_factor_sqrt(f.factor, f.sqrt_information, f.robust, f.label)
                .expect("validated");
            ids.push(id);
        }
        // chi2 the new factors add at the current estimate, before removals shift indices.
        let new_chi2 =
            solver::evaluate_chi2(&problem.factors()[first_new_factor..], &problem.values)
                .unwrap_or(f64::INFINITY);
        index.extend(problem, first_new_factor);
        for f in &problem.factors()[first_new_factor..] {
            seeds.extend_from_slice(f.variables());
        }
        if !prepared.remove.is_empty() {
            let remove: HashSet<FactorId> = prepared.remove.into_iter().collect();
            let keep: Vec<bool> = ids.iter().map(|id| !remove.contains(id)).collect();
            problem.retain_factors(|i| keep[i]);
            ids.retain(|id| !remove.contains(id));
            index.rebuild(problem);
        }
        for (key, fixed) in prepared.fix {
            problem.set_fixed(key, fixed).expect("validated");
        }
        for (key, v) in &prepared.guesses {
            let idx = problem.values.index_of(*key).expect("validated");
            problem.values.set(idx, v.as_ref());
            structural = true;
        }
        st.factors_since_solve += added;
        st.structural |= structural;
        // A batch that only adds factors whose total chi2 at the current (converged) estimate is
        // below the function tolerance of the whole cannot make a solve gain more than that
        // tolerance: the estimate stays the optimum to within what a solve would reach. This is
        // what makes appending an odometry-predicted pose free.
        if !adds_variables && added == 0 && !structural && !st.dirty {
            // An empty batch: whatever reflected the last one reflects this one (a `wait` on it
            // must not wait for a timer, or for ever under `manual`).
            st.solved_sequence = sequence;
            self.solved.send_replace(sequence);
            return;
        }
        let total = st.chi2.unwrap_or(0.0) + new_chi2;
        let negligible = new_chi2 <= st.options.function_tolerance * total || new_chi2 == 0.0;
        let was_converged = st.converged && !st.dirty && st.chi2.is_some();
        st.chi2 = st.chi2.map(|_| total);
        if was_converged && !structural && negligible {
            st.seeds.clear();
            st.solved_sequence = sequence;
            st.skipped_solves += 1;
            self.solved.send_replace(sequence);
        } else {
            st.dirty = true;
            st.converged = false;
        }
    }

    fn maybe_schedule(self: &Arc<Self>, st: &mut State) {
        if !st.dirty || st.scheduled || st.deleted {
            return;
        }
        if st.forced {
            return self.schedule(st);
        }
        match st.auto {
            AutoOptimize::EveryBatch {} => self.schedule(st),
            AutoOptimize::EveryNFactors { factors } => {
                if st.factors_since_solve >= factors {
                    self.schedule(st)
                }
            }
            AutoOptimize::EveryMs { milliseconds } => {
                if !st.timer_armed {
                    st.timer_armed = true;
                    let session = Arc::clone(self);
                    self.runtime.spawn(async move {
                        tokio::time::sleep(Duration::from_millis(milliseconds)).await;
                        let mut st = session.lock();
                        st.timer_armed = false;
                        if st.dirty && !st.scheduled && !st.deleted {
                            session.schedule(&mut st);
                        }
                    });
                }
            }
            AutoOptimize::Manual {} => {}
        }
    }

    fn schedule(self: &Arc<Self>, st: &mut State) {
        st.scheduled = true;
        let session = Arc::clone(self);
        if !self.pool.submit(Box::new(move || session.solve_once())) {
            st.scheduled = false; // the pool is shutting down
        }
    }

    /// Asks for a solve now, whatever the policy. Returns the sequence it will reflect and the
    /// number the solve will have (for [`Session::wait_solve`]).
    pub fn optimize_now(self: &Arc<Self>) -> Result<(u64, u64), ServiceError> {
        let mut st = self.lock();
        if st.deleted {
            return Err(ServiceError::not_found("session", &self.name));
        }
        st.dirty = true;
        st.converged = false;
        st.forced = true;
        // Asked for explicitly: the whole problem, not only the region the last updates reach
        // (region solves stop within their tolerance of the optimum; this one goes all the way).
        st.structural = true;
        if !st.scheduled {
            self.schedule(&mut st);
        }
        // A running solve started before this request; the one asked for is the next.
        Ok((st.sequence, st.solves + 1))
    }

    /// Waits until a solve reflecting `sequence` finished, at most `timeout`.
    pub async fn wait_solved(&self, sequence: u64, timeout: Duration) -> bool {
        let mut rx = self.solved.subscribe();
        tokio::time::timeout(timeout, rx.wait_for(|s| *s >= sequence))
            .await
            .is_ok_and(|r| r.is_ok())
    }

    /// Waits until solve number `solve` finished, at most `timeout`.
    pub async fn wait_solve(&self, solve: u64, timeout: Duration) -> bool {
        let mut rx = self.completed.subscribe();
        tokio::time::timeout(timeout, rx.wait_for(|n| *n >= solve))
            .await
            .is_ok_and(|r| r.is_ok())
    }

    /// Wakes every waiter (the session is going away or the service is stopping).
    pub(crate) fn release_waiters(&self) {
        self.solved.send_replace(u64::MAX);
        self.completed.send_replace(u64::MAX);
    }

    pub fn set_auto_optimize(self: &Arc<Self>, auto: AutoOptimize) -> Result<(), ServiceError> {
        if let AutoOptimize::EveryNFactors { factors: 0 } = auto {
            return Err(ServiceError::bad_request(
                "invalid_value",
                "factors",
                "every_n_factors needs factors >= 1",
            ));
        }
        if let AutoOptimize::EveryMs { milliseconds: 0 } = auto {
            return Err(ServiceError::bad_request(
                "invalid_value",
                "milliseconds",
                "every_ms needs milliseconds >= 1",
            ));
        }
        let mut st = self.lock();
        self.journal_auto_optimize(auto)?;
        st.auto = auto;
        self.maybe_schedule(&mut st);
        Ok(())
    }

    /// Stops the running solve after its current iteration; returns whether one was running.
    pub fn cancel(&self) -> bool {
        let st = self.lock();
        if st.solving {
            self.cancel.store(true, Ordering::SeqCst);
        }
        st.solving
    }

    pub(crate) fn mark_deleted(&self) {
        let mut st = self.lock();
        st.deleted = true;
        self.cancel.store(true, Ordering::SeqCst);
        drop(st);
        self.release_waiters();
    }

    pub fn estimate(&self, query: &EstimateQuery) -> Estimate {
        let st = self.lock();
        let range = query.from.unwrap_or(0)..=query.to.unwrap_or(Key::MAX);
        let since = query.since.unwrap_or(0);
        let variables = if range.start() > range.end() {
            Vec::new()
        } else {
            st.mirror
                .range(range)
                .filter(|(_, e)| query.since.is_none() || e.changed > since)
                .map(|(&k, e)| value_of(k, e))
                .collect()
        };
        Estimate {
            session: self.name.clone(),
            sequence: st.sequence,
            variables,
        }
    }

    pub fn stats(&self) -> SessionStats {
        let st = self.lock();
        SessionStats {
            session: self.name.clone(),
            kind: self.kind.name.into(),
            sequence: st.sequence,
            solved_sequence: st.solved_sequence,
            num_variables: st.mirror.len(),
            num_factors: st.live_factors.len(),
            pending_batches: st.pending.len(),
            solving: st.solving,
            solves: st.solves,
            skipped_solves: st.skipped_solves,
            chi2: st.chi2,
            converged: st.converged,
            auto_optimize: st.auto,
            options: st.options.clone(),
            // A damaged recovery outranks solve errors, and a later solve does not clear it.
            last_error: self.corruption().or(st.last_error.as_ref()).cloned(),
            last_summary: st.last_summary.clone(),
            recovering: self.is_recovering(),
            corrupt: self.corruption().is_some(),
            memory_bytes: self.memory_bytes_locked(&st),
        }
    }

    /// Estimated bytes this session holds: the estimate clients read, the problem (variables,
    /// factors with their square-root information), queued batches and the wire copies kept for
    /// snapshots. An estimate from sizes, not an allocator count.
    pub fn memory_bytes(&self) -> usize {
        let st = self.lock();
        self.memory_bytes_locked(&st)
    }

    fn memory_bytes_locked(&self, st: &State) -> usize {
        use std::mem::size_of;
        const NODE: usize = 48; // map/set node and allocation overhead
        let mirror: usize = st
            .mirror
            .values()
            .map(|e| size_of::<MirrorEntry>() + size_of::<Key>() + NODE + 8 * e.value.len())
            .sum();
        let factors = st.live_factors.len() * (size_of::<FactorId>() + NODE)
            + st.edges.len() * (size_of::<[Key; 2]>() + NODE)
            + st.factor_ids.len() * size_of::<FactorId>();
        let problem = st.problem.as_ref().map_or(st.problem_bytes, problem_bytes);
        let marginals = self
            .marginals_bytes
            .load(std::sync::atomic::Ordering::Relaxed) as usize;
        mirror + factors + problem + marginals + self.durable_memory_bytes()
    }
}

fn value_of(key: Key, e: &MirrorEntry) -> VariableValue {
    VariableValue {
        key,
        kind: e.kind.into(),
        value: e.value.clone(),
        changed: e.changed,
    }
}
