//! The session's mutable state, kept behind one lock: the problem (when no worker has it), the
//! mirror clients read, the queue of batches waiting for a running solve, and the bookkeeping
//! that decides when to solve next.

use std::collections::{BTreeMap, HashSet, VecDeque};
use std::time::Duration;

use super::batch::PreparedBatch;
use super::incremental::RegionIndex;
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
    pub(super) index: Option<RegionIndex>,
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
            index: Some(RegionIndex::default()),
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
        }
    }
}

/// Estimated bytes of a problem: variables (boxed, with their key index) and factors (boxed,
/// with keys, square-root information and label).
pub(super) fn problem_bytes(problem: &Problem) -> usize {
    use std::mem::size_of;
    let values = problem.values.len() * (size_of::<Box<dyn Variable>>() + 128);
    let factors: usize = problem
        .factors()
        .iter()
        .map(|f| {
            let r = f.factor.residual_dim();
            size_of::<crate::problem::FactorEntry>()
                + 96
                + 8 * (r * r + f.variables().len())
                + f.label.len()
        })
        .sum();
    values + factors
}
