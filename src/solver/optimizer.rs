//! The solver's entry points: [`optimize`], [`optimize_within`] and [`optimize_warm`]. This file
//! owns the preparation of a solve (gauge, ordering, layout, symbolic factorisation, memory
//! refusal, initialisation) and hands the iteration itself to [`super::iterations`]; the Summary
//! is assembled in [`super::summary`].

use std::borrow::Borrow;
use std::ops::ControlFlow;
use std::time::Instant;

use faer::sparse::linalg::SupernodalThreshold;

use super::budget::{Budget, Unlimited};
use super::cholesky::SparseCholesky;
use super::gauge::anchor_components;
use super::initialize::{chordal_estimate, take_estimate};
use super::iterations::{Iterations, StepTimes};
use super::linear::LinearSolver;
use super::linearize::{free_adjacency, SystemLayout};
use super::options::{Initialization, Method, SolverOptions};
use super::schur::{self, ImplicitSchur, SchurSolver};
use super::stopping::stopped;
use super::structure::{BlockOrdering, ScalarRows};
use super::summary::{IterationReport, Run, Summary, Timings};
use super::warm::OrderingCache;
use super::{evaluate_chi2, evaluate_chi2_within, SolverError};
use crate::problem::FactorEntry;
use crate::problem::{Gauge, Problem, Values};

// The warm re-solve reaches these through this module; they live with their own concepts.
pub(super) use super::summary::Context;

/// Optimises `problem.values` in place. `on_iteration` sees every iteration as it finishes and
/// may stop the solve there (`ControlFlow::Break`): the values are then those of the last accepted
/// step and the termination reason is [`TerminationReason::Interrupted`](super::TerminationReason::Interrupted).
pub fn optimize(
    problem: &mut Problem,
    options: &SolverOptions,
    on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
) -> Result<Summary, SolverError> {
    optimize_from(problem, options, on_iteration, None, &Unlimited)
}

/// [`optimize`] within a [`Budget`]: the solve checks it between small pieces of work (not only
/// between iterations) and stops there with an `interrupted` termination and the last accepted
/// estimate; a solve whose factorisation needs more memory than the budget allows is refused
/// before any numeric work ([`SolverError::MemoryLimit`]).
pub fn optimize_within(
    problem: &mut Problem,
    options: &SolverOptions,
    on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
    budget: &dyn Budget,
) -> Result<Summary, SolverError> {
    optimize_from(problem, options, on_iteration, None, budget)
}

/// [`optimize`] for values already near the optimum (a session re-solving after a small update).
/// It may also stop after an undamped step (the quadratic model's minimum) whose actual decrease
/// matched the model's prediction to within `function_tolerance × chi2`: the model was then
/// accurate over the step, so the step landed at the model's minimum and a further one cannot
/// gain more than that tolerance. (A damped step stops short of the model's minimum, so the
/// match says nothing there.)
/// This saves the confirming iteration a cold solve needs; the initialisation option is ignored.
/// `ordering` carries the elimination order between the re-solves of a growing problem.
pub fn optimize_warm(
    problem: &mut Problem,
    options: &SolverOptions,
    on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
    ordering: &mut OrderingCache,
) -> Result<Summary, SolverError> {
    optimize_warm_within(problem, options, on_iteration, ordering, &Unlimited)
}

/// [`optimize_warm`] within a [`Budget`], as [`optimize_within`].
pub fn optimize_warm_within(
    problem: &mut Problem,
    options: &SolverOptions,
    on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
    ordering: &mut OrderingCache,
    budget: &dyn Budget,
) -> Result<Summary, SolverError> {
    let options = SolverOptions {
        initialization: Initialization::None,
        ..options.clone()
    };
    optimize_from(problem, &options, on_iteration, Some(ordering), budget)
}

fn optimize_from(
    problem: &mut Problem,
    options: &SolverOptions,
    on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
    cache: Option<&mut OrderingCache>,
    budget: &dyn Budget,
) -> Result<Summary, SolverError> {
    let warm = cache.is_some();
    let start = Instant::now();
    let mut timings = Timings::default();
    let (fixed, gauge_fixed) = match problem.gauge {
        Gauge::AnchorComponents => anchor_components(problem.factors(), &problem.values),
        Gauge::Free => (
            (0..problem.values.len())
                .map(|v| problem.values.is_fixed(v))
                .collect(),
            Vec::new(),
        ),
    };
    let initial_chi2 = initial_chi2(problem.factors(), &problem.values, budget)?;
    if !initial_chi2.is_finite() {
        return Err(SolverError::NonFiniteInitialCost);
    }

    let System {
        ordering,
        layout,
        chol,
    } = analyze(problem, options, &fixed, cache, budget)?;
    timings.preprocess_seconds = start.elapsed().as_secs_f64();

    let init_start = Instant::now();
    let estimate = chordal_estimate(
        problem,
        &fixed,
        &ordering,
        chol.block_supernodes(),
        options.initialization,
        budget,
    );
    timings.initialization_seconds = init_start.elapsed().as_secs_f64();

    let mut values = std::mem::take(&mut problem.values);
    // The trial buffer is whichever of the given values and the estimate is not started from.
    let mut solver =
        Iterations::with_trial(&layout, chol, timings, Values::default(), warm, budget);
    let mut times = StepTimes::default();
    let start_point = start_point(
        &mut solver,
        problem.factors(),
        &mut values,
        estimate,
        options.initialization,
        initial_chi2,
        &mut times,
    );
    let outcome = start_point.and_then(|(label, initialized_chi2, first)| {
        // Stopped in the first linearisation: the values are the given ones, whose chi2 is
        // known (evaluating it again would cost what the budget just refused).
        if first.is_break() {
            return Ok((label, initialized_chi2, initial_chi2, stopped(0)));
        }
        let (chi2, termination) = solver.run_linearized(
            problem.factors(),
            &mut values,
            options,
            on_iteration,
            first,
            times,
        )?;
        Ok((label, initialized_chi2, chi2, termination))
    });
    problem.values = values;
    let (init_label, initialized_chi2, chi2, termination) = outcome?;
    let run = solver.finish(chi2, termination);
    Ok(run.summary(
        options,
        &layout,
        problem.factors(),
        &problem.values,
        Context {
            start,
            initialization: init_label,
            gauge_fixed,
            initial_chi2,
            initialized_chi2,
            region: None,
        },
    ))
}

/// The structure's half of a solve: one fill-reducing order of the variable graph (it serves
/// the initialisation and the solve; with a Schur complement the eliminated variables come
/// first), the system's layout and its symbolic factorisation. They only need the structure,
/// so they come before the initialisation: a solve too big for its memory budget is refused
/// before any numeric work.
struct System {
    ordering: BlockOrdering,
    layout: SystemLayout,
    chol: LinearSolver,
}

fn analyze(
    problem: &Problem,
    options: &SolverOptions,
    fixed: &[bool],
    cache: Option<&mut OrderingCache>,
    budget: &dyn Budget,
) -> Result<System, SolverError> {
    let mut schur_plan = schur::plan(
        problem.factors(),
        &problem.values,
        fixed,
        &problem.eliminate,
        options.linear_solver,
        || schur::explicit_limit(budget.max_memory_bytes()),
    );
    let ordering = match (&mut schur_plan, cache) {
        // Moved out, not copied: the Schur solvers read only the plan's reduced order (a copy
        // of the whole graph was 24 M entries in 2 M lists at 5 000 cameras).
        (Some(plan), _) => std::mem::take(&mut plan.ordering),
        (None, Some(cache)) => cache.ordering(problem.factors(), fixed),
        (None, None) => BlockOrdering::amd(free_adjacency(problem.factors(), fixed)),
    };
    // Dogleg's model product is the one reader of H's scalar rows in a Schur solve.
    let rows = if schur_plan.is_some() && options.method != Method::Dogleg {
        ScalarRows::Omitted
    } else {
        ScalarRows::Listed
    };
    let mut layout =
        SystemLayout::with_ordering(problem.factors(), &problem.values, fixed, &ordering, rows);
    let threads = options.thread_count();
    if threads > 1 {
        layout.use_threads(problem.factors(), threads);
    }
    let chol = match &schur_plan {
        Some(plan) if plan.implicit => {
            let mut schur = ImplicitSchur::new(&layout.pattern, plan);
            schur.use_threads(threads);
            LinearSolver::ImplicitSchur(schur)
        }
        Some(plan) => {
            let mut schur = SchurSolver::new(&layout.pattern, plan)?;
            schur.use_threads(threads);
            LinearSolver::Schur(schur)
        }
        // Supernodal on every pattern we measured: the block ordering makes variables supernodes
        // (M3500: 2.8 ms vs 5.1 ms simplicial; intel 0.58 vs 1.44).
        None => LinearSolver::Sparse(SparseCholesky::analyze(
            &layout.pattern,
            SupernodalThreshold::FORCE_SUPERNODAL,
        )?),
    };
    if let Some(limit) = budget.max_memory_bytes() {
        let estimated = super::budget::estimate_memory(problem, &layout, &chol, options);
        if estimated > limit {
            return Err(SolverError::MemoryLimit {
                estimated,
                limit,
                factor_nnz: chol.factor_nnz(),
            });
        }
    }
    Ok(System {
        ordering,
        layout,
        chol,
    })
}

/// What [`start_point`] returns.
type StartPoint = (String, Option<f64>, ControlFlow<(), f64>);

/// Where the iterations start, linearised there: the chordal estimate when its chi2 is low
/// enough (the first linearisation there gives that chi2; a separate evaluation costs a tenth
/// of a small solve), else the given values (a rejected estimate costs a second
/// linearisation). `values` ends as the start, `solver.trial` as the other one. Returns the
/// initialisation's label, the chi2 it reached, and the first linearisation's outcome.
fn start_point<E: Borrow<FactorEntry> + Sync>(
    solver: &mut Iterations,
    factors: &[E],
    values: &mut Values,
    estimate: Result<Values, String>,
    initialization: Initialization,
    initial_chi2: f64,
    times: &mut StepTimes,
) -> Result<StartPoint, SolverError> {
    let estimate = match estimate {
        Ok(estimate) => estimate,
        Err(label) => {
            solver.trial = values.clone();
            return solver
                .linearize_at(factors, values, times)
                .map(|first| (label, None, first));
        }
    };
    let given = std::mem::replace(values, estimate);
    match solver.linearize_at(factors, values, times)? {
        ControlFlow::Continue(chi2) => match take_estimate(initialization, chi2, initial_chi2) {
            Ok(label) => {
                solver.trial = given;
                Ok((label, Some(chi2), ControlFlow::Continue(chi2)))
            }
            Err(label) => {
                solver.trial = std::mem::replace(values, given);
                *times = StepTimes::default();
                solver
                    .linearize_at(factors, values, times)
                    .map(|first| (label, Some(initial_chi2), first))
            }
        },
        // The budget stopped the solve while linearising: it ends at the given values.
        ControlFlow::Break(()) => {
            solver.trial = std::mem::replace(values, given);
            let label = "none (stopped by the solve's budget)".to_string();
            Ok((label, None, ControlFlow::Break(())))
        }
    }
}

#[allow(clippy::too_many_arguments)]
pub(super) fn iterate<E: Borrow<FactorEntry> + Sync>(
    values: &mut Values,
    factors: &[E],
    layout: &SystemLayout,
    chol: LinearSolver,
    timings: Timings,
    options: &SolverOptions,
    on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
    warm: bool,
    budget: &dyn Budget,
) -> Result<Run, SolverError> {
    let mut solver = Iterations::new(layout, chol, timings, values, warm, budget);
    let (chi2, termination) = solver.run(factors, values, options, on_iteration)?;
    Ok(solver.finish(chi2, termination))
}

/// The cost at the given values, checked like a linearisation: with costly factors this one
/// evaluation takes seconds. A budget that stops it because it was cancelled (time left) fails
/// the solve with nothing changed; one out of time lets it finish, so that the solve answers
/// with an interrupted Summary at the given values, as it would a moment later.
pub(super) fn initial_chi2<E: Borrow<FactorEntry> + Sync>(
    factors: &[E],
    values: &Values,
    budget: &dyn Budget,
) -> Result<f64, SolverError> {
    match evaluate_chi2_within(factors, values, budget)? {
        ControlFlow::Continue(chi2) => Ok(chi2),
        ControlFlow::Break(()) if budget.remaining().is_some_and(|left| left.is_zero()) => {
            Ok(evaluate_chi2(factors, values)?)
        }
        ControlFlow::Break(()) => Err(SolverError::Interrupted),
    }
}
