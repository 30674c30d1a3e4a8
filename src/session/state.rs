//! The session's mutable state, kept behind one lock, split by the concept that changes each
//! part: the problem and its engine ([`Model`], moved to a worker during solves), the mirror
//! clients read ([`Mirror`], written by accepted batches and refreshed by solves), what the
//! next solve covers and when it runs ([`Schedule`], with the phase machine of
//! `schedule_state`), what the solves so far reached ([`SolveResults`]), and every producer's
//! progress ([`Producers`]).

use std::collections::{BTreeMap, HashSet, VecDeque};
use std::time::Duration;

use super::batch::PreparedBatch;
use super::incremental::IncrementalSolver;
use super::producers::Producers;
use super::schedule_state::SolveSchedule;
use super::MirrorEntry;
use crate::api::catalogue::SessionKind;
use crate::api::wire::{AutoOptimize, FactorId};
use crate::problem::{Key, Problem, Variable};
use crate::solver::{self, SolverOptions};

pub(super) struct State {
    pub(super) options: SolverOptions,
    pub(super) auto: AutoOptimize,
    pub(super) model: Model,
    pub(super) mirror: Mirror,
    pub(super) schedule: Schedule,
    pub(super) results: SolveResults,
    /// Exactly-once ingest: every producer's progress.
    pub(super) producers: Producers,
    /// Several robots in the session (`robots` at creation), else `None`.
    pub(super) robots: Option<super::robots::Robots>,
    /// Possibly wrong loop closures, held out of the problem until decided.
    pub(super) outliers: super::outliers::Outliers,
    /// The latency budget and its provisional answers (`max_update_ms`), when set.
    pub(super) latency: Option<super::provisional::Latency>,
}

/// The problem and its incremental engine: here between solves, on a worker during one.
/// Written by batches applied to it and by solves.
pub(super) struct Model {
    /// `None` while a worker has it (with `index`).
    pub(super) problem: Option<Problem>,
    pub(super) index: Option<IncrementalSolver>,
    /// Id of each factor of the problem, parallel to `problem.factors()`.
    pub(super) factor_ids: Vec<FactorId>,
    /// Variables the last full solve fixed to remove the gauge freedom.
    pub(super) gauge: Vec<Key>,
    /// The problem's size when it was last here (it is on a worker during solves).
    pub(super) bytes: usize,
}

/// Every accepted variable and factor as clients see them, with the sequence and factor ids
/// handed out. Written by accepted batches (before they reach the problem) and refreshed from
/// solves; batches validate against it, reads are served from it.
pub(super) struct Mirror {
    pub(super) entries: BTreeMap<Key, MirrorEntry>,
    /// Σ [`heap_values`](super::mirror::heap_values) over the entries (numbers beyond the
    /// inline capacity), kept as entries are added and guessed (a solve's refresh keeps each
    /// value's kind, so its length), for [`Mirror::bytes`].
    pub(super) heap_values: usize,
    pub(super) live_factors: HashSet<FactorId>,
    /// Live factors between two pose-shaped variables (what the web view draws as edges).
    pub(super) edges: BTreeMap<FactorId, [Key; 2]>,
    pub(super) next_factor_id: FactorId,
    /// The highest sequence accepted (the mirror reflects every batch up to it).
    pub(super) sequence: u64,
}

/// What the next solve covers and when it runs. Written by batches (what they touch) and by
/// the scheduling (`schedule.rs`, `solve.rs`).
pub(super) struct Schedule {
    /// When the next solve runs (see `schedule_state`).
    pub(super) phase: SolveSchedule,
    /// Variables (dense indices) touched by factors added since the last solve.
    pub(super) seeds: Vec<usize>,
    /// Since the last solve, something other than additions changed (removals, fixes, guesses):
    /// the next solve is of the whole problem.
    pub(super) structural: bool,
    /// What region re-solves left unsolved at their boundaries (see `incremental`).
    pub(super) region_debt: f64,
    pub(super) factors_since_solve: usize,
    /// Batches accepted while a worker has the problem, applied when it comes back.
    pending: VecDeque<(u64, PreparedBatch, Vec<FactorId>)>,
    /// Factors in `pending`.
    pending_factors: usize,
    /// Time the current solve spent in earlier (preempted) turns.
    pub(super) carried: Duration,
    /// The client asked for a solve (`optimize`) since the last one started.
    pub(super) asked: bool,
    /// A bundle adjustment rested with values given since its last restart: the next solve
    /// restarts from them, yielding to any batch (see `bundle`).
    pub(super) restart_when_idle: bool,
}

/// What the solves so far reached. Written by solves, and by batches a solve need not see.
pub(super) struct SolveResults {
    pub(super) solves: u64,
    pub(super) skipped_solves: u64,
    /// Highest sequence a finished solve (or a skipped one) reflects.
    pub(super) solved_sequence: u64,
    pub(super) chi2: Option<f64>,
    pub(super) converged: bool,
    pub(super) last_error: Option<String>,
    pub(super) last_summary: Option<solver::Summary>,
}

impl State {
    /// A new session's state: an empty problem of its kind, nothing solved yet.
    pub(super) fn new(
        kind: &'static SessionKind,
        options: SolverOptions,
        auto: AutoOptimize,
    ) -> Self {
        State {
            options,
            auto,
            model: Model {
                problem: Some(Problem::with_gauge(kind.gauge).eliminating(kind.eliminate)),
                index: Some(IncrementalSolver::default()),
                factor_ids: Vec::new(),
                gauge: Vec::new(),
                bytes: 0,
            },
            mirror: Mirror {
                entries: BTreeMap::new(),
                heap_values: 0,
                live_factors: HashSet::new(),
                edges: BTreeMap::new(),
                next_factor_id: 0,
                sequence: 0,
            },
            schedule: Schedule {
                phase: SolveSchedule::default(),
                seeds: Vec::new(),
                structural: true,
                region_debt: 0.0,
                factors_since_solve: 0,
                pending: VecDeque::new(),
                pending_factors: 0,
                carried: Duration::ZERO,
                asked: false,
                restart_when_idle: false,
            },
            results: SolveResults {
                solves: 0,
                skipped_solves: 0,
                solved_sequence: 0,
                chi2: None,
                converged: true,
                last_error: None,
                last_summary: None,
            },
            producers: Producers::default(),
            robots: None,
            outliers: Default::default(),
            latency: None,
        }
    }
}

impl Model {
    /// Takes the problem and its engine out for a worker.
    pub(super) fn take(&mut self) -> (Problem, IncrementalSolver) {
        (
            self.problem
                .take()
                .expect("one solve per session at a time"),
            self.index.take().expect("kept with the problem"),
        )
    }

    /// Puts them back, remembering their size for while they are out again.
    pub(super) fn put_back(&mut self, problem: Problem, index: IncrementalSolver) {
        self.bytes = problem_bytes(&problem) + index.engine_bytes();
        self.problem = Some(problem);
        self.index = Some(index);
    }

    /// Estimated bytes of the problem and its engine (their size when last here while out).
    pub(super) fn memory_bytes(&self) -> usize {
        match (&self.problem, &self.index) {
            (Some(problem), Some(index)) => problem_bytes(problem) + index.engine_bytes(),
            _ => self.bytes,
        }
    }
}

impl Mirror {
    /// Estimated bytes of the entries (entries, keys, map nodes, values), in O(1).
    pub(super) fn bytes(&self) -> usize {
        self.entries.len() * MIRROR_ENTRY_BYTES + 8 * self.heap_values
    }

    /// The ids of a batch's `count` factors: `given` (a snapshot's), else the next ones; the
    /// next id handed out is past all of them.
    pub(super) fn assign_factor_ids(
        &mut self,
        given: Option<Vec<FactorId>>,
        count: usize,
    ) -> Vec<FactorId> {
        let ids: Vec<FactorId> =
            given.unwrap_or_else(|| (0..count as u64).map(|k| self.next_factor_id + k).collect());
        self.next_factor_id = ids
            .iter()
            .map(|id| id + 1)
            .fold(self.next_factor_id, u64::max);
        ids
    }
}

impl Schedule {
    /// Queues a batch behind the running solve (the worker has the problem).
    pub(super) fn queue_batch(
        &mut self,
        sequence: u64,
        prepared: PreparedBatch,
        ids: Vec<FactorId>,
    ) {
        self.pending_factors += prepared.factor_count();
        self.pending.push_back((sequence, prepared, ids));
        self.phase.mark_dirty();
    }

    /// The oldest queued batch, to apply now that the problem is back.
    pub(super) fn next_queued(&mut self) -> Option<(u64, PreparedBatch, Vec<FactorId>)> {
        let next = self.pending.pop_front()?;
        self.pending_factors -= next.1.factor_count();
        Some(next)
    }

    /// Drops the queued batches (a deleted session's would only cost CPU for nobody).
    pub(super) fn drop_queued(&mut self) {
        self.pending.clear();
        self.pending_factors = 0;
    }

    pub(super) fn queued_batches(&self) -> usize {
        self.pending.len()
    }

    pub(super) fn queued_factors(&self) -> usize {
        self.pending_factors
    }
}

impl SolveResults {
    /// A solve finished at `chi2`; `stopped`: why it stopped short (the time limit), which
    /// leaves it unconverged, else the last error is cleared.
    pub(super) fn solved(&mut self, chi2: f64, converged: bool, stopped: Option<String>) {
        self.chi2 = Some(chi2);
        self.converged = converged && stopped.is_none();
        self.last_error = stopped;
    }

    /// A solve failed: `message` says why; the estimate is the last good one, unconverged.
    pub(super) fn failed(&mut self, message: String) {
        self.converged = false;
        self.last_error = Some(message);
    }

    /// Whatever reflected the last batch reflects `sequence` (it changed nothing to solve).
    pub(super) fn reflected(&mut self, sequence: u64) {
        self.solved_sequence = sequence;
    }

    /// A solve of the batch `sequence` would not gain more than its tolerance: skipped.
    pub(super) fn skipped(&mut self, sequence: u64) {
        self.solved_sequence = sequence;
        self.skipped_solves += 1;
    }
}

/// Map node and allocation overhead.
const NODE: usize = 48;
const MIRROR_ENTRY_BYTES: usize =
    std::mem::size_of::<MirrorEntry>() + std::mem::size_of::<Key>() + NODE;

/// Estimated bytes of a problem: variables (boxed, with their key index) and factors (boxed,
/// with keys, square-root information and label). O(1): the problem keeps its factors' sum.
pub(super) fn problem_bytes(problem: &Problem) -> usize {
    problem.values.len() * VARIABLE_BYTES + problem.factor_bytes()
}

/// Estimated bytes of one variable in a problem (the box, the key and its index entry).
const VARIABLE_BYTES: usize = std::mem::size_of::<Box<dyn Variable>>() + 128;

#[cfg(test)]
mod tests {
    //! The maintained byte counts equal what walking the session finds, after additions,
    //! removals, fixes, guesses, solves (the problem leaves and comes back) and snapshots.

    use std::time::Duration;

    use serde_json::json;

    use super::super::{Durability, Session};
    use super::*;
    use crate::api::wire::Batch;
    use crate::journal::{JournalConfig, SessionDir};

    /// What [`problem_bytes`] estimated before it was kept: a walk over every factor.
    fn walked_problem_bytes(problem: &Problem) -> usize {
        let factors: usize = problem
            .factors()
            .iter()
            .map(|f| {
                let r = f.factor.residual_dim();
                std::mem::size_of::<crate::problem::FactorEntry>()
                    + 96
                    + 8 * (r * r + f.variables().len())
                    + f.label.len()
            })
            .sum();
        problem.values.len() * VARIABLE_BYTES + factors
    }

    fn walked_mirror_bytes(st: &State) -> usize {
        st.mirror
            .entries
            .values()
            .map(|e| MIRROR_ENTRY_BYTES + 8 * crate::session::mirror::heap_values(&e.value))
            .sum()
    }

    fn check(session: &Session, step: &str) {
        let st = session.lock();
        assert_eq!(
            st.mirror.bytes(),
            walked_mirror_bytes(&st),
            "mirror, {step}"
        );
        let problem = st.model.problem.as_ref().expect("no solve running");
        assert_eq!(
            problem_bytes(problem),
            walked_problem_bytes(problem),
            "problem, {step}"
        );
        assert!(problem_bytes(problem) > 0, "{step}");
        drop(st);
        let durable = session.durable.lock().unwrap();
        if let Some((kept, walked)) = durable.as_ref().and_then(|d| d.bytes_kept_and_walked()) {
            assert_eq!(kept, walked, "journal side, {step}");
        }
    }

    fn batch(value: serde_json::Value) -> Batch {
        serde_json::from_value(value).unwrap()
    }

    #[test]
    fn maintained_byte_counts_equal_the_walked_ones() {
        let (runtime, pool, session) = crate::session::test_session("bytes");
        let state_dir = std::env::temp_dir().join(format!("factord-bytes-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&state_dir);
        let request =
            serde_json::from_value(json!({"session": "bytes", "kind": "pose_graph_2d"})).unwrap();
        let dir = SessionDir::create(&state_dir, "bytes", &request, None).unwrap();
        let journal = dir.open_journal(crate::journal::Fsync::Never).unwrap();
        let config = JournalConfig {
            snapshot_every: 4,
            ..JournalConfig::default()
        };
        session.attach(Durability {
            dir,
            journal,
            config,
        });
        let mut ids = Vec::new();
        for k in 0..40u64 {
            let mut factors = vec![json!({"type": "between_se2", "keys": [k, k + 1],
                "measurement": [1.0, 0.0, 0.1], "sigmas": [0.1, 0.1, 0.05]})];
            if k % 7 == 6 {
                factors.push(json!({"type": "between_se2", "keys": [k - 5, k + 1],
                    "measurement": [5.0, 0.2, 0.5], "information": [100, 0, 0, 100, 0, 400]}));
            }
            let variables = if k == 0 {
                json!([{"key": 0, "kind": "se2", "value": [0, 0, 0], "fixed": true},
                       {"key": 1, "kind": "se2"}])
            } else {
                json!([{"key": k + 1, "kind": "se2"}])
            };
            let (ack, _) = session
                .apply_batch(batch(json!({"variables": variables, "factors": factors})))
                .unwrap();
            ids.extend(ack.factor_ids);
            check(&session, &format!("after adding pose {}", k + 1));
        }
        let solve = |step: &str| {
            let (_, n) = session.optimize_now().unwrap();
            assert!(runtime.block_on(session.wait_solve(n, Duration::from_secs(30))));
            check(&session, step);
        };
        solve("after a solve");
        session
            .apply_batch(batch(json!({"remove_factors": [ids[3], ids[10], ids[11]]})))
            .unwrap();
        check(&session, "after removals");
        session
            .apply_batch(batch(
                json!({"guesses": [{"key": 5, "value": [4.0, 1.0, 0.3]}],
                "fix": [7], "unfix": [0]}),
            ))
            .unwrap();
        check(&session, "after a guess and fixes");
        solve("after a second solve");
        // Snapshots ran on the way (every 4 entries): wait for the last to give its base back.
        for _ in 0..500 {
            if session
                .durable
                .lock()
                .unwrap()
                .as_ref()
                .and_then(|d| d.bytes_kept_and_walked())
                .is_some()
            {
                break;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        check(&session, "after the snapshots");
        assert!(state_dir.join("sessions/bytes/snapshot.json").exists());
        let memory = session.memory_bytes();
        assert!(memory > 40 * MIRROR_ENTRY_BYTES, "{memory}");
        drop(session);
        pool.shutdown(Duration::from_secs(5));
    }
}
