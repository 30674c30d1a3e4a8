//! The session's mutable state, kept behind one lock: the problem (when no worker has it), the
//! mirror clients read, the queue of batches waiting for a running solve, and the bookkeeping
//! that decides when to solve next.

use std::collections::{BTreeMap, HashSet, VecDeque};
use std::time::Duration;

use super::batch::PreparedBatch;
use super::incremental::IncrementalSolver;
use super::producers::Producers;
use super::MirrorEntry;
use crate::api::catalogue::SessionKind;
use crate::api::wire::{AutoOptimize, FactorId};
use crate::problem::{Key, Problem, Variable};
use crate::solver::{self, SolverOptions};

pub(super) struct State {
    pub(super) options: SolverOptions,
    pub(super) auto: AutoOptimize,
    /// `None` while a worker has it (with `index`).
    pub(super) problem: Option<Problem>,
    pub(super) index: Option<IncrementalSolver>,
    /// Variables (dense indices) touched by factors added since the last solve.
    pub(super) seeds: Vec<usize>,
    /// Since the last solve, something other than additions changed (removals, fixes, guesses):
    /// the next solve is of the whole problem.
    pub(super) structural: bool,
    /// What region re-solves left unsolved at their boundaries (see `incremental`).
    pub(super) region_debt: f64,
    /// Variables the last full solve fixed to remove the gauge freedom.
    pub(super) gauge: Vec<Key>,
    /// Id of each factor of the problem, parallel to `problem.factors()`.
    pub(super) factor_ids: Vec<FactorId>,
    pub(super) mirror: BTreeMap<Key, MirrorEntry>,
    /// Σ [`heap_values`](super::mirror::heap_values) over the mirror (numbers beyond the
    /// inline capacity), kept as entries are added and guessed (a solve's refresh keeps each
    /// value's kind, so its length), for [`State::mirror_bytes`].
    pub(super) mirror_values: usize,
    pub(super) live_factors: HashSet<FactorId>,
    /// Live factors between two pose-shaped variables (what the web view draws as edges).
    pub(super) edges: BTreeMap<FactorId, [Key; 2]>,
    pub(super) next_factor_id: FactorId,
    pub(super) sequence: u64,
    pub(super) solved_sequence: u64,
    pub(super) pending: VecDeque<(u64, PreparedBatch, Vec<FactorId>)>,
    pub(super) pending_factors: usize,
    pub(super) factors_since_solve: usize,
    /// Changed since the last solve in a way a solve could improve.
    pub(super) dirty: bool,
    /// Queued on or running in the pool.
    pub(super) scheduled: bool,
    /// A solve was asked for (`optimize`): it runs whatever the policy.
    pub(super) forced: bool,
    pub(super) solving: bool,
    pub(super) timer_armed: bool,
    pub(super) deleted: bool,
    pub(super) solves: u64,
    pub(super) skipped_solves: u64,
    pub(super) chi2: Option<f64>,
    pub(super) converged: bool,
    pub(super) last_error: Option<String>,
    pub(super) last_summary: Option<solver::Summary>,
    /// The problem's size when it was last here (it is on a worker during solves).
    pub(super) problem_bytes: usize,
    /// Time the current solve spent in earlier (preempted) turns.
    pub(super) solve_carried: Duration,
    /// Exactly-once ingest: every producer's progress.
    pub(super) producers: Producers,
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
            problem: Some(Problem::with_gauge(kind.gauge).eliminating(kind.eliminate)),
            index: Some(IncrementalSolver::default()),
            seeds: Vec::new(),
            structural: true,
            region_debt: 0.0,
            gauge: Vec::new(),
            factor_ids: Vec::new(),
            mirror: BTreeMap::new(),
            mirror_values: 0,
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
            producers: Producers::default(),
        }
    }
}

impl State {
    /// Estimated bytes of the mirror (entries, keys, map nodes, values), in O(1).
    pub(super) fn mirror_bytes(&self) -> usize {
        self.mirror.len() * MIRROR_ENTRY_BYTES + 8 * self.mirror_values
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
            .values()
            .map(|e| MIRROR_ENTRY_BYTES + 8 * crate::session::mirror::heap_values(&e.value))
            .sum()
    }

    fn check(session: &Session, step: &str) {
        let st = session.lock();
        assert_eq!(
            st.mirror_bytes(),
            walked_mirror_bytes(&st),
            "mirror, {step}"
        );
        let problem = st.problem.as_ref().expect("no solve running");
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
