//! The incremental engine of a session: a block Cholesky factor that lives between updates,
//! refactored only along the elimination-tree paths an update touches, with the touched part
//! reordered so that new variables stay last, and relinearisation only of what moved.
//!
//! The estimate is `θ ⊕ Δ`: θ is the linearisation point (per variable), Δ the solution of the
//! normal equations linearised there. An update
//! 1. linearises the new factors at θ (a new variable's θ is its initial guess);
//! 2. relinearises ("fluid relinearisation"): every variable whose `Δ` exceeds the threshold
//!    (max-norm of its tangent) moves its θ to `θ ⊕ Δ`, and the factors touching it are
//!    linearised again;
//! 3. eliminates again the columns of the variables whose `H` entries changed and their
//!    ancestors in the elimination tree, reordered with the new factors' variables last
//!    (`ordering`, `block_factor`); the rest of the factor is kept as it is. An update
//!    that relinearised nothing may instead add its factors by a rank update along those
//!    paths, without reordering (`add_factors`);
//! 4. solves the whole linear system: forward substitution only where the factor changed (the
//!    rest of `y` depends only on unchanged subtrees), back substitution from the root down
//!    into every subtree whose separator moved by more than the wildfire threshold.
//!
//! Passes 2–4 repeat while a variable's step still exceeds the relinearisation threshold (up
//! to `max_passes`), so an update ends at a Gauss-Newton fixed point to that threshold. A
//! session asks for a tighter threshold when it is idle (`polish`), which ends at the batch
//! optimum.

mod add_factors;
mod beside;
mod block_factor;
mod dense;
mod elimination_cost;
mod innovation;
mod linearized;
mod ordering;
mod refactor_pass;
mod relinearize_budget;
mod report;
mod subtree_updates;
mod summary;
mod whole_order;

use std::time::Instant;

use block_factor::BlockFactor;
use linearized::{linearize_factor, Linearized};
pub use report::UpdateReport;
pub use summary::UpdateContext;

use super::summary::non_negative_chi2;
use super::SolverError;
use crate::problem::Problem;
use crate::variables::Variable;

/// Per linearised factor: its three vectors' headers and allocations, and its index entries.
const LINEARIZED_OVERHEAD: usize = 3 * 24 + 3 * 16 + 8;
/// Per variable: θ (boxed), its bookkeeping vectors and the column's headers.
const VARIABLE_OVERHEAD: usize = 160;
/// From this many factors to linearise again, a pass does it on a second thread beside its
/// ordering (a thread costs tens of microseconds; a factor about one).
const LINEARIZE_BESIDE_FROM: usize = 256;

/// How an update relinearises and solves.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UpdateParams {
    /// A variable is relinearised when its step's max-norm exceeds this (iSAM2:
    /// `relinearizeThreshold`, 0.1 by default there).
    pub relinearize_threshold: f64,
    /// Back substitution stops descending where a separator moved by less than this
    /// (iSAM2's wildfire threshold, 0.001 there). 0 solves every column below a change.
    pub wildfire_threshold: f64,
    /// Relinearise-and-solve rounds at most.
    pub max_passes: usize,
    /// A pass relinearises, largest steps first (up to the first that does not fit), only as
    /// many variables as fit in about this many scalar columns of the factor (their
    /// elimination-tree paths to the root, each column counting its variable's dimension: a 3D
    /// pose's column costs more to refactor than a 2D pose's); `usize::MAX` takes every
    /// variable above the threshold. It bounds what one update costs, so that an idle
    /// session's polish runs in steps: a streamed update waits behind one step at most.
    pub relinearize_scalars: usize,
    /// When at least this many variables, and more than a quarter of them, are past the
    /// threshold (a correction of the whole map), the pass relinearises none of them and
    /// reports them as deferred (`UpdateReport::deferred_variables`); `usize::MAX` never
    /// defers. The caller decides how many updates in a row may defer.
    pub defer_from: usize,
}

impl Default for UpdateParams {
    fn default() -> Self {
        Self {
            relinearize_threshold: 0.01,
            wildfire_threshold: 1e-7,
            max_passes: 4,
            relinearize_scalars: usize::MAX,
            defer_from: usize::MAX,
        }
    }
}

/// The engine: linearisation point, linearised factors, factor, and the solution.
#[derive(Debug, Default)]
pub struct IncrementalEngine {
    theta: Vec<Box<dyn Variable>>,
    /// In the linear system (not fixed by the client, not a gauge anchor).
    free: Vec<bool>,
    /// First scalar of each variable in `delta`, `y` (free ones; dimension 0 otherwise).
    offset: Vec<usize>,
    dims: Vec<usize>,
    delta: Vec<f64>,
    /// Per variable, the max-norm of its step in `delta`, kept as back substitution writes it:
    /// relinearisation reads this array instead of walking every variable's slice of `delta`
    /// (at 100k 2D poses that walk took 0.4–0.7 ms of every update).
    step: Vec<f64>,
    /// Per scalar of `delta`, the value the column's subtree was last solved against (see
    /// `BlockFactor::back_substitute`).
    propagated: Vec<f64>,
    y: Vec<f64>,
    /// Per row, what the stored columns contribute to its forward substitution
    /// (`BlockFactor::forward`).
    partial: Vec<f64>,
    linearized: Vec<Linearized>,
    /// Factors `relinearize` moved the linearisation point of, linearised again by the next
    /// `solve_pass` (beside its ordering, on a second thread, when there are many).
    pending: Vec<usize>,
    by_variable: Vec<Vec<u32>>,
    factor: BlockFactor,
    /// Σ chi2 of the linearised factors at θ, and yᵀy (their difference is the model chi2).
    residual_chi2: f64,
    yty: f64,
    scratch: super::linearize::Scratch,
    /// Variables whose estimate the last update wrote.
    changed: Vec<usize>,
    /// Σ residual dimensions and Σ free variables over the factors (the Summary's sizes).
    residuals: usize,
    jacobian_blocks: usize,
    /// Free variables (columns of the factor).
    columns: usize,
    /// Bytes of the linearised factors (kept as they are added).
    linearized_bytes: usize,
    /// Flops of the last refactoring pass, and of the rank updates since (see `add_factors`).
    refactor_flops: f64,
    update_flops: f64,
    /// Scratch marks indexed by variable.
    mark: Vec<bool>,
    last: Vec<bool>,
    local: Vec<u32>,
    /// Which sizes of refactored parts were worth a nested-dissection trial last time.
    trials: ordering::TrialHistory,
    /// Scalar nonzeros of the factor right after it was last ordered whole, and the size below
    /// which its order is left alone (`None`: the default; see `whole_order`).
    whole_order_nnz: usize,
    whole_order_from: Option<usize>,
}

impl IncrementalEngine {
    /// Builds the engine at `problem`'s values (usually a converged batch solve) with the
    /// variables marked in `fixed` held constant, and writes `θ ⊕ Δ` back into the problem.
    pub fn new(problem: &mut Problem, fixed: &[bool]) -> Result<(Self, UpdateReport), SolverError> {
        let mut engine = Self::default();
        let report = engine.advance(problem, Some(fixed), &UpdateParams::default())?;
        Ok((engine, report))
    }

    /// As [`IncrementalEngine::new`], relinearising and solving as `params` say: a session
    /// builds one on a copy of its problem at its estimate, beside its updates, to relinearise
    /// the whole map off their path (`session::relinearize_beside`).
    pub fn new_with(
        problem: &mut Problem,
        fixed: &[bool],
        params: &UpdateParams,
    ) -> Result<Self, SolverError> {
        let mut engine = Self::default();
        engine.advance(problem, Some(fixed), params)?;
        Ok(engine)
    }

    /// Writes θ ⊕ Δ of every free variable this engine knows into `problem`, which holds at
    /// least those variables in the same order: an engine built on a copy of a problem gives
    /// the problem its estimate when it takes over (the held ones were never moved).
    pub fn write_estimate(&self, problem: &mut Problem) {
        for v in (0..self.theta.len()).filter(|&v| self.free[v]) {
            self.write_variable(problem, v);
        }
    }

    fn write_variable(&self, problem: &mut Problem, v: usize) {
        let (o, d) = (self.offset[v], self.dims[v]);
        let estimate = problem.values.variable_mut(v);
        estimate.assign_from(self.theta[v].as_ref());
        estimate.retract(&self.delta[o..o + d]);
    }

    /// Memory the engine holds, from counts it keeps (O(1)): the factor's values and block
    /// indices, the linearised factors, the linearisation point and the solution vectors, and
    /// the dense fronts' buffers.
    pub fn memory_bytes(&self) -> usize {
        let variables = self.theta.len() * VARIABLE_OVERHEAD + 32 * self.delta.len();
        let factor = 8 * self.factor.nnz()
            + 8 * self.jacobian_blocks
            + self.factor.kept_update_bytes()
            + self.factor.front_scratch_bytes();
        variables + factor + self.linearized_bytes
    }

    /// Variables this engine knows (those added later join at the next update).
    pub fn variables(&self) -> usize {
        self.theta.len()
    }

    /// Takes the variables and factors appended to `problem` since the last call, relinearises
    /// and solves (see the module documentation), and writes the changed estimates into the
    /// problem. On `Err` the engine is unusable: rebuild it with [`IncrementalEngine::new`].
    pub fn update(
        &mut self,
        problem: &mut Problem,
        params: &UpdateParams,
    ) -> Result<UpdateReport, SolverError> {
        self.advance(problem, None, params)
    }

    /// The variables whose estimate the last update wrote into the problem.
    pub fn changed(&self) -> &[usize] {
        &self.changed
    }

    fn advance(
        &mut self,
        problem: &mut Problem,
        fixed_at_start: Option<&[bool]>,
        params: &UpdateParams,
    ) -> Result<UpdateReport, SolverError> {
        let mut report = UpdateReport::default();
        let start = Instant::now();
        let known = self.theta.len();
        report.new_variables = problem.values.len() - known;
        let mut touched = self.add_variables(problem, fixed_at_start);
        let first_new = self.linearized.len();
        report.new_factors = problem.factors().len() - first_new;
        self.linearize_new_factors(problem, &mut touched)?;
        // The new factors' variables are eliminated last (they are where the next update lands).
        let constrained = newest(&touched, MAX_LAST);
        for &v in &constrained {
            self.last[v] = true;
        }
        report.linearize_seconds = start.elapsed().as_secs_f64();
        if known > 0 && self.fill_outgrew_its_order() {
            self.touch_every_column(&mut touched);
            report.whole_reorder = true;
        }
        let mut changed = Vec::new();
        for pass in 0..params.max_passes.max(1) {
            if pass > 0 || known > 0 {
                self.relinearize(problem, params, &mut touched, &mut report);
            }
            if touched.is_empty() {
                break;
            }
            report.passes += 1;
            let only_adds = pass == 0
                && known > 0
                && report.relinearized_variables == 0
                && !report.whole_reorder;
            if !(only_adds
                && self.add_factors(
                    problem,
                    first_new,
                    known,
                    params,
                    &mut report,
                    &mut changed,
                )?)
            {
                self.solve_pass(problem, &mut touched, params, &mut report, &mut changed)?;
            }
            touched.clear();
            // Only the first pass carries new factors; later ones reorder freely.
            for &v in &constrained {
                self.last[v] = false;
            }
        }
        if known == 0 || report.whole_reorder {
            self.whole_order_nnz = self.factor.nnz();
        }
        debug_assert!(
            self.pending.is_empty(),
            "a relinearisation always reaches solve_pass"
        );
        self.publish(problem, changed, &mut report);
        Ok(report)
    }

    /// Takes the variables appended to `problem` since the last update (θ at their values, Δ
    /// zero); returns the free ones, which the next solve must reach.
    fn add_variables(&mut self, problem: &Problem, fixed_at_start: Option<&[bool]>) -> Vec<usize> {
        let (known, n) = (self.theta.len(), problem.values.len());
        for v in known..n {
            let variable = problem.values.variable(v);
            let is_fixed = match fixed_at_start {
                Some(fixed) => fixed[v],
                None => problem.values.is_fixed(v),
            };
            let d = if is_fixed { 0 } else { variable.tangent_dim() };
            self.theta.push(variable.clone_box());
            self.free.push(!is_fixed);
            self.columns += usize::from(!is_fixed);
            self.offset.push(self.delta.len());
            self.dims.push(d);
            self.delta.resize(self.delta.len() + d, 0.0);
            self.step.push(0.0);
            self.propagated.resize(self.delta.len(), 0.0);
            self.y.resize(self.y.len() + d, 0.0);
            self.partial.resize(self.partial.len() + d, 0.0);
            self.by_variable.push(Vec::new());
        }
        self.factor.grow(&self.dims);
        self.mark.resize(n, false);
        self.last.resize(n, false);
        self.local.resize(n, 0);
        (known..n).filter(|&v| self.free[v]).collect()
    }

    /// Linearises the factors appended to `problem` since the last update at θ and adds their
    /// free variables to `touched`.
    fn linearize_new_factors(
        &mut self,
        problem: &Problem,
        touched: &mut Vec<usize>,
    ) -> Result<(), SolverError> {
        let first_new = self.linearized.len();
        for (f, entry) in problem.factors().iter().enumerate().skip(first_new) {
            let mut lin = Linearized::default();
            linearize_factor(entry, &self.theta, &mut self.scratch, &mut lin)?;
            self.residual_chi2 += lin.chi2;
            self.residuals += entry.factor.residual_dim();
            self.linearized_bytes += LINEARIZED_OVERHEAD
                + 8 * (lin.gram.len() + lin.gradient.len() + lin.col_offset.len());
            self.linearized.push(lin);
            for &v in entry.variables() {
                self.by_variable[v].push(f as u32);
                if self.free[v] {
                    self.jacobian_blocks += 1;
                    touched.push(v);
                }
            }
        }
        Ok(())
    }

    /// Writes θ ⊕ Δ of what changed into the problem, and the update's totals into `report`.
    fn publish(
        &mut self,
        problem: &mut Problem,
        mut changed: Vec<usize>,
        report: &mut UpdateReport,
    ) {
        changed.sort_unstable();
        changed.dedup();
        for &v in &changed {
            self.write_variable(problem, v);
        }
        report.changed_variables = changed.len();
        self.changed = changed;
        report.factor_nnz = self.factor.nnz();
        report.columns = self.columns;
        report.model_chi2 = non_negative_chi2(self.residual_chi2 - self.yty);
        report.max_delta = self.step.iter().fold(0.0f64, |m, &s| m.max(s));
    }

    /// Moves θ of the free variables whose step exceeds the threshold (within the budget, see
    /// [`UpdateParams::relinearize_scalars`]) to `θ ⊕ Δ`, leaves their factors in `pending`
    /// (the next `solve_pass` linearises them again) and adds the factors' variables to
    /// `touched`.
    fn relinearize(
        &mut self,
        problem: &Problem,
        params: &UpdateParams,
        touched: &mut Vec<usize>,
        report: &mut UpdateReport,
    ) {
        let start = Instant::now();
        let mut moved: Vec<(usize, f64)> = self
            .step
            .iter()
            .enumerate()
            .filter(|&(_, &step)| step > params.relinearize_threshold)
            .map(|(v, &step)| (v, step))
            .collect();
        if moved.len() >= params.defer_from && moved.len() * 4 > self.theta.len() {
            report.deferred_variables = moved.len();
            moved.clear();
        }
        if params.relinearize_scalars < self.delta.len() {
            self.within_budget(problem, &mut moved, params.relinearize_scalars);
        }
        let mut factors = Vec::new();
        for &(v, _) in &moved {
            let (o, d) = (self.offset[v], self.dims[v]);
            self.theta[v].retract(&self.delta[o..o + d]);
            // The step now lives in θ. No column outside this update's refactored part has a
            // block in v's row (such a column's subtree would hold one of v's factors, all of
            // which are linearised again here), so nothing solved earlier depends on v's Δ.
            self.delta[o..o + d].fill(0.0);
            self.step[v] = 0.0;
            self.propagated[o..o + d].fill(0.0);
            report.relinearized_variables += 1;
            factors.extend(self.by_variable[v].iter().map(|&f| f as usize));
        }
        factors.sort_unstable();
        factors.dedup();
        report.relinearized_factors += factors.len();
        let entries = problem.factors();
        for &f in &factors {
            touched.extend(entries[f].variables().iter().filter(|&&v| self.free[v]));
        }
        self.pending = factors;
        report.linearize_seconds += start.elapsed().as_secs_f64();
    }
}

/// At most this many variables of an update are eliminated last. A usual update brings a pose,
/// its predecessor and the old ends of a loop closure or two; an update that takes in thousands
/// of poses at once (a session whose exact solve fell behind, a client's bulk upload) ordered
/// them all last, with the old ends of their closures, and eliminating the map below them
/// filled them in as one dense root clique. On the 300 000-pose city, 3 000 poses added at once
/// to the first 220 000 took 10.1 s of factorisation and left 52.4 M scalars (peak 5.0 GB);
/// with only the newest 8 last, 0.84 s and 35.1 M (1.6 GB). Streamed with a latency budget,
/// such updates followed each other (each slower one taking in more) until the process was
/// killed for memory near pose 250 000. The rest are ordered with the part they are refactored
/// in.
const MAX_LAST: usize = 8;

/// The `keep` newest of `variables` (the highest indices: variables are numbered as created),
/// where the next update's odometry lands.
fn newest(variables: &[usize], keep: usize) -> Vec<usize> {
    let mut newest = variables.to_vec();
    if newest.len() > keep {
        newest.sort_unstable_by(|a, b| b.cmp(a));
        newest.truncate(keep);
    }
    newest
}
