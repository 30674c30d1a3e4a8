//! Re-solving only as far as an update reaches.
//!
//! Pose-graph sessions keep a [`solver::incremental::IncrementalEngine`] next to the problem:
//! after a batch solve the engine is built at its solution, and every later solve of an
//! additions-only update is one engine update (refactor what the update touched, relinearise
//! what moved). When an update leaves steps above the convergence threshold, the session
//! schedules a *polish*: engine updates with a tight threshold that end at the batch optimum,
//! run in bounded steps while no batch arrives (a batch arriving meanwhile waits for the current
//! step only, see [`POLISH`] and `solve`). Removals,
//! fixes and guesses, and any engine failure, go through a batch solve, which rebuilds it.
//!
//! Sessions the engine does not fit (bundle adjustment: Schur complement, free gauge) use
//! regions:
//! After an update that only added variables and factors to a converged problem, the estimate
//! needs to change mostly near the new factors. So a re-solve starts with a small *region*: the
//! variables within reach of the new factors (breadth-first over the factor graph), optimised
//! with everything else held fixed. Then the ring of variables just outside the region is
//! checked: the Newton decrement `bᵀH⁻¹b` of letting that ring move (with the region held at its
//! new values) is the chi2 a further, larger solve could still gain at the boundary. When it is
//! below the function tolerance of the total chi2, the region was large enough; otherwise the
//! region grows fourfold, up to the whole problem. iSAM2 makes the same bet with its wildfire
//! threshold (only variables whose update exceeds it are recomputed); here the test is on the
//! cost, the same criterion as the solver's own convergence test.

use std::collections::VecDeque;
use std::ops::ControlFlow;

use std::time::Instant;

use super::relinearize_beside::{self, Beside};
use crate::problem::{Gauge, Key, Problem};
use crate::solver::incremental::{IncrementalEngine, UpdateContext, UpdateParams};
use crate::solver::summary::non_negative_chi2;
use crate::solver::{self, IterationReport, SolverError, SolverOptions, Summary};

/// Problems smaller than this are always re-solved whole: a region would not pay off.
const MIN_VARIABLES_FOR_REGIONS: usize = 150;
/// First region size (variables); each retry is four times larger.
const FIRST_REGION: usize = 128;
/// A region the update's reach makes larger than asked for and than this fraction of the
/// problem is not tried: the whole solve it would spare costs little more, and testing it costs
/// more (the Newton decrement on its ring).
/// A BAL camera streamed into a small map reaches most of it at once: problem-16's 16th camera
/// touched 4 802 of 22 122 variables, and one region try (solve 0.12 s, ring 0.80 s) cost six
/// times the whole solve (0.14 s).
const MAX_REGION_FRACTION: f64 = 1.0 / 8.0;
/// Region solves leave up to `function_tolerance × chi2` each at their boundary; once what they
/// left adds up to this many tolerances, the next re-solve is of the whole problem.
const DEBT_LIMIT: f64 = 10.0;

/// An update on the request path: relinearise what moved more than this (max-norm of the
/// tangent step), in one round. The estimate then sits within ~3e-5 relative chi2 of the
/// optimum (tests/library/incremental_engine.rs `threshold_sweep`); the polish closes the rest.
const STREAM: UpdateParams = UpdateParams {
    relinearize_threshold: 0.05,
    wildfire_threshold: 1e-5,
    max_passes: 1,
    relinearize_scalars: usize::MAX,
    defer_from: DEFER_FROM_VARIABLES,
};
/// A streamed update (`UpdateParams::defer_from`) leaves relinearisation to a later one when at
/// least this many variables, and more than a quarter of them, moved past [`STREAM`]'s
/// threshold: a correction of the whole map. The loop closures that follow such a correction
/// keep correcting the same map, and relinearising it at each of them refactors most of the map
/// each time (M3500: bursts of 1 000–2 000-variable relinearisations; the 100k graph at 65k
/// poses: 62 000 variables, 99 times in 530 updates). Deferred, they merge into one. The
/// linear system is still solved whole at every update, at the older linearisation point, and
/// the polish relinearises once the session is idle. Smaller corrections are cheap to
/// relinearise at once, and deferring them slowed sphere2500 (its corrections stay below 600
/// variables).
const DEFER_FROM_VARIABLES: usize = 1024;
/// Streamed updates in a row that may defer a correction; the next one relinearises it, unless
/// the map is being relinearised beside them (see [`START_BESIDE_AFTER`]).
const MAX_DEFERRED_UPDATES: u32 = 16;
/// The streamed update that defers a correction for this many updates in a row starts
/// relinearising the whole map beside the updates (`relinearize_beside`); the first update
/// after it is done takes it over. Two robots streamed into M3500 (`split.py --robots 2
/// --wait`), against relinearising on the request path: p99 4.6–5.1 against 6.6–7.1 ms over
/// HTTP, 4.7–5.2 against 6.1–7.2 ms over zenoh, totals within 2 %. Started at the first
/// deferring update, relinearisations ran back to back through a long correction and were the
/// slower to land, which left answers further from the optimum (`incremental_stream
/// --accuracy-every 25` on M3500: the excess's mean 1.5e-3, max 0.13, against 6.3e-4 and
/// 2.5e-2).
const START_BESIDE_AFTER: u32 = 8;
/// Streamed updates in a row that may defer while the map is relinearised beside them: past
/// this, the relinearisation beside them is too slow to wait for (it only runs on a core
/// nothing else wants), and the update relinearises on its own path. Answers that waited up to
/// 32 updates were as close to the optimum as with 16 (stop 75); with 64, further.
const MAX_DEFERRED_BESIDE: u32 = 32;
/// How the map is relinearised beside the updates: as a streamed update that defers nothing,
/// in one round. It gets only the CPU the server and its clients leave, and the updates that
/// arrive meanwhile are taken in after it (`relinearize_beside`), so a second round mostly
/// delayed it: two robots streamed into M3500 over HTTP, with two rounds 12–17 of ~50 per
/// stream did not land within [`MAX_DEFERRED_BESIDE`] updates, and each of those 33rd updates
/// relinearised 1 500–2 900 variables on its own path (4.5–10.8 ms); with one, 1–2. Before
/// the thread took in the arrivals, one round left the update taking it over 600–900
/// variables to relinearise on the request path; now the catch-up does that beside it.
const BESIDE: UpdateParams = UpdateParams {
    max_passes: 1,
    defer_from: usize::MAX,
    ..STREAM
};

/// A polish, or a solve the client asked for: steps below this are the optimum.
const CONVERGED_STEP: f64 = 1e-4;
/// One step of a polish: relinearise the largest steps above [`CONVERGED_STEP`] that fit in the
/// step's column budget, refactor, solve exactly. Steps repeat while the session stays idle
/// until none is left. After a long stream nearly every variable has drifted past the tight
/// threshold; relinearising them all at once took 0.5 s at 10k poses, and a batch that arrived
/// meanwhile waited for all of it (an engine update cannot be interrupted).
const POLISH: UpdateParams = UpdateParams {
    relinearize_threshold: CONVERGED_STEP,
    wildfire_threshold: 0.0,
    max_passes: 1,
    relinearize_scalars: FIRST_POLISH_STEP_SCALARS,
    defer_from: usize::MAX,
};
/// Scalar columns of the factor the first polish step after an update may refactor for its
/// relinearisation (2048 columns of 2D poses, 1024 of 3D poses): about what a large streamed
/// update refactors (a loop closure at 10k 2D poses), so that a batch arriving during it waits
/// about one update more. Each further step of the same idle spell may take twice as many: the
/// session has been idle at least as long as the steps before took, so a batch waits behind a
/// step about as long as the session had been idle, and a long idle spell converges in a few
/// wide steps rather than many narrow ones.
const FIRST_POLISH_STEP_SCALARS: usize = 2048 * 3;

/// What a session keeps between re-solves, next to its problem: the incremental engine, for
/// every variable (dense index) the factors (indices) that touch it, the elimination order of
/// full re-solves, and whether idle time should polish.
#[derive(Debug, Default)]
pub(crate) struct IncrementalSolver {
    by_variable: Vec<Vec<usize>>,
    ordering: solver::OrderingCache,
    engine: Option<IncrementalEngine>,
    /// The last engine update left steps above [`CONVERGED_STEP`]: polish when idle.
    pub polish: bool,
    /// Polish steps since the last streamed update (each may refactor twice the last).
    polish_steps: u32,
    /// Streamed updates in a row that deferred a correction (see [`DEFER_FROM_VARIABLES`]).
    deferred_updates: u32,
    /// The whole map relinearised beside the streamed updates, while it runs, and a reference
    /// held by each thread that does it (one at a time, see `Beside::start`).
    beside: Option<Beside>,
    beside_threads: std::sync::Arc<()>,
    /// The engine's updates are off the request path (a session with a latency budget): a
    /// deferred correction is then not relinearised beside them, where the copy and the second
    /// engine would only cost memory (the budgeted 100 000-pose stream peaked at 1.81 GB against
    /// 1.04 GB, its p99 ratio 1.87 against 1.85).
    pub off_request_path: bool,
    /// A bundle adjustment's values as its client gave them (see `bundle`).
    pub given: super::bundle::GivenValues,
}

impl IncrementalSolver {
    /// Records factors `from..` of `problem` (call after appending them).
    pub fn extend(&mut self, problem: &Problem, from: usize) {
        self.by_variable.resize(problem.values.len(), Vec::new());
        for (f, entry) in problem.factors().iter().enumerate().skip(from) {
            for &v in entry.variables() {
                self.by_variable[v].push(f);
            }
        }
    }

    /// A full re-solve of the whole problem from its current values, reusing the ordering.
    pub fn solve_whole(
        &mut self,
        problem: &mut Problem,
        options: &SolverOptions,
        on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
        budget: &dyn solver::Budget,
    ) -> Result<Summary, SolverError> {
        solver::optimize_warm_within(problem, options, on_iteration, &mut self.ordering, budget)
    }

    /// Rebuilds from scratch (after factors were removed, which renumbers them).
    pub fn rebuild(&mut self, problem: &Problem) {
        self.by_variable.clear();
        self.extend(problem, 0);
        // The engine's factor numbering is gone too; the next batch solve builds it again.
        self.engine = None;
        self.beside = None;
    }

    /// What the incremental engine and the given values hold (0 without them).
    pub fn engine_bytes(&self) -> usize {
        self.engine
            .as_ref()
            .map_or(0, IncrementalEngine::memory_bytes)
            + self.given.bytes()
    }

    /// After a batch solve: the engine, built at its solution with the client's fixed
    /// variables and the solve's gauge anchors held. A problem it does not fit gets none.
    pub fn rebuild_engine(&mut self, problem: &mut Problem, gauge: &[Key]) {
        self.engine = None;
        self.beside = None;
        self.polish = false;
        self.polish_steps = 0;
        self.deferred_updates = 0;
        if !problem.eliminate.is_empty() || problem.gauge != Gauge::AnchorComponents {
            return;
        }
        let fixed = held_fixed(problem, gauge);
        match IncrementalEngine::new(problem, &fixed) {
            Ok((engine, _)) => self.engine = Some(engine),
            // The batch solve succeeded, so this is a degenerate system the batch solver's
            // damping handled: keep solving in batch.
            Err(e) => tracing::debug!("no incremental engine for this problem: {e}"),
        }
    }

    /// The innovation distance of a factor not in the problem's engine yet (see
    /// `IncrementalEngine::innovation`); `None` without an engine, for a factor on a variable the
    /// engine has not taken in, or one it cannot evaluate.
    pub fn innovation(
        &self,
        problem: &Problem,
        entry: &crate::problem::FactorEntry,
    ) -> Option<f64> {
        self.engine
            .as_ref()?
            .innovation(problem, entry)
            .ok()
            .flatten()
    }

    /// After a solve of the whole problem: the engine built again at its answer when it
    /// converged.
    pub fn adopt_whole(&mut self, problem: &mut Problem, summary: Summary) -> Resolved {
        if summary.converged {
            self.rebuild_engine(problem, &summary.used.gauge_fixed);
        }
        Resolved::whole(summary)
    }

    /// One engine update of an additions-only change (`tight`: polish, or a solve the client
    /// asked for). `None` when there is no engine; an `Err` drops it (the caller solves in
    /// batch, which builds it again).
    pub fn update_engine(
        &mut self,
        problem: &mut Problem,
        total_chi2: f64,
        tight: bool,
        options: &SolverOptions,
        gauge: &[Key],
        on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
    ) -> Option<Result<Resolved, SolverError>> {
        self.engine.as_ref()?;
        let start = Instant::now();
        let took_over =
            relinearize_beside::take_over(&mut self.beside, &mut self.engine, problem, tight);
        if took_over {
            self.deferred_updates = 0;
        }
        let params = self.update_params(tight);
        let engine = self.engine.as_mut()?;
        let report = match engine.update(problem, &params) {
            Ok(report) => report,
            Err(e) => {
                self.engine = None;
                self.beside = None;
                return Some(Err(e));
            }
        };
        self.deferred_updates = if report.deferred_variables > 0 {
            self.deferred_updates + 1
        } else {
            0
        };
        if report.deferred_variables > 0
            && !self.off_request_path
            && self.beside.is_none()
            && self.deferred_updates >= START_BESIDE_AFTER
        {
            let fixed = held_fixed(problem, gauge);
            self.beside = Beside::start(problem, fixed, (BESIDE, STREAM), &self.beside_threads);
        } else if let Some(beside) = self.beside.as_mut() {
            beside.send_appended(problem);
        }
        let converged = report.max_delta <= CONVERGED_STEP;
        self.polish = !converged;
        let summary = engine.summary(
            problem,
            &report,
            UpdateContext {
                options,
                gauge,
                initial_chi2: total_chi2,
                seconds: start.elapsed().as_secs_f64(),
                converged,
                threshold: CONVERGED_STEP,
            },
        );
        // One update is one Gauss-Newton step: streamed like a solver iteration (an engine
        // update is not interruptible, so what the callback answers does not matter).
        let _ = on_iteration(&IncrementalEngine::iteration(&report, total_chi2));
        Some(Ok(Resolved {
            total_chi2: summary.final_chi2,
            converged,
            // The engine taken over gave every variable its estimate.
            moved: (!took_over).then(|| engine.changed().to_vec()),
            summary,
        }))
    }

    /// How this update relinearises: a polish step (`tight`), or a streamed update that may
    /// defer a correction of the whole map.
    fn update_params(&mut self, tight: bool) -> UpdateParams {
        if tight {
            self.polish_steps += 1;
            return UpdateParams {
                relinearize_scalars: POLISH
                    .relinearize_scalars
                    .saturating_mul(1 << (self.polish_steps - 1).min(20)),
                ..POLISH
            };
        }
        self.polish_steps = 0;
        // Deferred long enough, this update relinearises the correction itself.
        let most = if self.beside.is_some() {
            MAX_DEFERRED_BESIDE
        } else {
            MAX_DEFERRED_UPDATES
        };
        if self.deferred_updates < most {
            return STREAM;
        }
        self.beside = None;
        UpdateParams {
            defer_from: usize::MAX,
            ..STREAM
        }
    }
}

/// Per variable, whether solves hold it: fixed by the client, or a gauge anchor of the last
/// full solve (`gauge`).
pub(crate) fn held_fixed(problem: &Problem, gauge: &[Key]) -> Vec<bool> {
    let mut fixed: Vec<bool> = (0..problem.values.len())
        .map(|v| problem.values.is_fixed(v))
        .collect();
    for key in gauge {
        if let Some(v) = problem.values.index_of(*key) {
            fixed[v] = true;
        }
    }
    fixed
}

/// How a re-solve went.
pub(crate) struct Resolved {
    /// The summary of the last solve that ran (a region's or the whole problem's).
    pub summary: Summary,
    /// chi2 of the whole problem afterwards.
    pub total_chi2: f64,
    pub converged: bool,
    /// The variables that may have moved (a region), or `None` for all.
    pub moved: Option<Vec<usize>>,
}

impl Resolved {
    /// A solve of the whole problem: every variable may have moved.
    pub fn whole(summary: Summary) -> Self {
        Resolved {
            total_chi2: summary.final_chi2,
            converged: summary.converged,
            moved: None,
            summary,
        }
    }
}

/// Re-solves `problem` after an additions-only update touching variables `seeds`.
/// `anchors[v]` says whether variable `v` is held fixed in any solve (fixed by the client, or the
/// gauge anchor of its component); `total_chi2` is the whole problem's chi2 now. `debt` carries
/// the boundary gains that accepted regions left behind, between calls.
#[allow(clippy::too_many_arguments)]
pub(crate) fn resolve(
    problem: &mut Problem,
    index: &mut IncrementalSolver,
    seeds: &[usize],
    anchors: &[bool],
    total_chi2: f64,
    debt: &mut f64,
    options: &SolverOptions,
    on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
    budget: &dyn solver::Budget,
) -> Result<Resolved, SolverError> {
    let n = problem.values.len();
    let mut size = FIRST_REGION;
    // The whole problem's chi2 as regions move things (each region solve reports its own).
    let mut total = total_chi2;
    let in_debt = *debt > DEBT_LIMIT * options.function_tolerance * total_chi2;
    if n >= MIN_VARIABLES_FOR_REGIONS && !seeds.is_empty() && !in_debt {
        while size * 3 < n {
            let region = grow_region(problem, index, seeds, size);
            // Whole layers: the update's own reach may be wider than the size asked for.
            if region.len() > size && region.len() as f64 > MAX_REGION_FRACTION * n as f64 {
                break;
            }
            let (fixed, inside) = held_outside(anchors, &region);
            let factors = factors_touching(index, &region);
            let summary = match solver::optimize_region_within(
                problem,
                &fixed,
                &factors,
                options,
                on_iteration,
                budget,
            ) {
                Ok(summary) => summary,
                // A region without an anchor (a new component): solve the whole problem.
                Err(SolverError::IndeterminateSystem { .. }) => break,
                Err(e) => return Err(e),
            };
            total = non_negative_chi2(total - (summary.initial_chi2 - summary.final_chi2));
            if summary.termination.reason == solver::TerminationReason::Interrupted {
                return Ok(Resolved {
                    converged: false,
                    total_chi2: total,
                    moved: Some(region),
                    summary,
                });
            }
            let gain = ring_gain(problem, index, &factors, &inside, anchors)?;
            if gain <= options.function_tolerance * total {
                *debt += gain;
                // Report the whole problem's chi2 (the iteration log keeps the region's).
                let mut summary = summary;
                summary.initial_chi2 = total_chi2;
                summary.final_chi2 = total;
                return Ok(Resolved {
                    converged: summary.converged,
                    total_chi2: total,
                    moved: Some(region),
                    summary,
                });
            }
            // Every size up to the region's own would grow the same region again.
            size = 4 * size.max(region.len());
        }
    }
    let summary = index.solve_whole(problem, options, on_iteration, budget)?;
    *debt = 0.0;
    Ok(Resolved::whole(summary))
}

/// What a region solve holds fixed (the anchors and everything outside `region`), and which
/// variables are inside it.
fn held_outside(anchors: &[bool], region: &[usize]) -> (Vec<bool>, Vec<bool>) {
    let mut fixed: Vec<bool> = anchors.to_vec();
    let mut inside = vec![false; anchors.len()];
    for &v in region {
        inside[v] = true;
    }
    for (v, f) in fixed.iter_mut().enumerate() {
        *f |= !inside[v];
    }
    (fixed, inside)
}

/// What a Newton step on the ring just outside a solved region (its variables free in the
/// whole problem, reached by the region's `factors`) would still gain.
fn ring_gain(
    problem: &Problem,
    index: &IncrementalSolver,
    factors: &[usize],
    inside: &[bool],
    anchors: &[bool],
) -> Result<f64, SolverError> {
    let ring: Vec<usize> = factors
        .iter()
        .flat_map(|&f| problem.factors()[f].variables().iter().copied())
        .filter(|&v| !inside[v] && !anchors[v])
        .collect();
    let mut ring_fixed = vec![true; inside.len()];
    for &v in &ring {
        ring_fixed[v] = false;
    }
    let ring_factors = factors_touching(index, &ring);
    solver::newton_decrement(problem, &ring_fixed, &ring_factors)
}

/// Up to about `size` variables, breadth-first from `seeds` (whole layers, so the region is a
/// ball in the factor graph).
fn grow_region(
    problem: &Problem,
    index: &IncrementalSolver,
    seeds: &[usize],
    size: usize,
) -> Vec<usize> {
    let n = problem.values.len();
    let mut seen = vec![false; n];
    let mut region = Vec::with_capacity(size * 2);
    let mut queue: VecDeque<(usize, usize)> = VecDeque::new();
    for &s in seeds {
        if !seen[s] {
            seen[s] = true;
            queue.push_back((s, 0));
        }
    }
    let mut layer_done = usize::MAX;
    while let Some((v, depth)) = queue.pop_front() {
        if depth > layer_done {
            break;
        }
        region.push(v);
        if region.len() >= size {
            layer_done = depth;
        }
        for &f in &index.by_variable[v] {
            for &w in problem.factors()[f].variables() {
                if !seen[w] {
                    seen[w] = true;
                    queue.push_back((w, depth + 1));
                }
            }
        }
    }
    region
}

/// Every factor touching one of `variables`, once, in index order.
fn factors_touching(index: &IncrementalSolver, variables: &[usize]) -> Vec<usize> {
    let mut factors: Vec<usize> = variables
        .iter()
        .flat_map(|&v| index.by_variable[v].iter().copied())
        .collect();
    factors.sort_unstable();
    factors.dedup();
    factors
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solver::budget::Unlimited;

    /// A chain of `n` 2D poses at their odometry (the optimum), pose 0 fixed, but for the last
    /// pose, 0.3 m off.
    fn chain(n: usize) -> (Problem, IncrementalSolver) {
        let mut text = String::new();
        for i in 0..n {
            let y = if i == n - 1 { 0.3 } else { 0.0 };
            text += &format!("VERTEX_SE2 {i} {i} {y} 0\n");
        }
        for i in 1..n {
            text += &format!("EDGE_SE2 {} {i} 1 0 0 100 0 0 100 0 100\n", i - 1);
        }
        text += "FIX 0\n";
        let path = std::path::Path::new("chain.g2o");
        let problem = crate::io::g2o::parse(&[(path, &text)]).unwrap().problem;
        let mut index = IncrementalSolver::default();
        index.extend(&problem, 0);
        (problem, index)
    }

    fn resolve_from(seeds: &[usize], n: usize) -> Resolved {
        let (mut problem, mut index) = chain(n);
        let anchors = held_fixed(&problem, &[]);
        let total = problem.chi2();
        resolve(
            &mut problem,
            &mut index,
            seeds,
            &anchors,
            total,
            &mut 0.0,
            &SolverOptions::default(),
            &mut |_| ControlFlow::Continue(()),
            &Unlimited,
        )
        .unwrap()
    }

    #[test]
    fn a_small_reach_is_re_solved_as_a_region_and_a_wide_one_whole() {
        let n = 1000;
        // A new pose at the end: a region of the chain's last poses.
        let near = resolve_from(&[n - 1], n);
        let region = near.summary.used.region_variables;
        assert_eq!(region, Some(FIRST_REGION));
        assert!(near.total_chi2 < 1e-12, "{}", near.total_chi2);
        // Seeds over a quarter of the problem (a camera that sees most of a small map): no
        // region is tried, the whole problem is solved.
        let seeds: Vec<usize> = (0..n).step_by(4).collect();
        let wide = resolve_from(&seeds, n);
        assert!(wide.moved.is_none() && wide.summary.used.region_variables.is_none());
        assert!(wide.total_chi2 < 1e-12, "{}", wide.total_chi2);
    }
}
