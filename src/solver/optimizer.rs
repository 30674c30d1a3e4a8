//! The iteration loop: Gauss-Newton, Levenberg-Marquardt (Nielsen's gain-ratio damping) and
//! Powell's Dogleg over one cached linear system.
//!
//! Costs are chi2 = Σ ρ(‖r‖²) (no ½). For a step Δ solving (H + λD)Δ = b with b = −Jᵀr the
//! model decrease is L(0) − L(Δ) = 2Δᵀb − ΔᵀHΔ = Δᵀb + λΔᵀDΔ; the gain ratio
//! ρ = (F(x) − F(x ⊕ Δ)) / (L(0) − L(Δ)) decides acceptance and the next λ or radius.

use std::borrow::Borrow;
use std::ops::ControlFlow;
use std::time::Instant;

use faer::sparse::linalg::SupernodalThreshold;

use super::budget::{Budget, FactorCost, Unlimited};
use super::cholesky::{NotPositiveDefinite, SparseCholesky};
use super::gauge::anchor_components;
use super::initialize::run_initialization;
use super::linear::{LinearSolver, SchurReport};
use super::linearize::{
    free_adjacency, linearize_within, symmetric_multiply, Scratch, SystemLayout,
};
use super::options::{Initialization, Method, SolverOptions};
use super::schur::{self, SchurSolver};
use super::structure::BlockOrdering;
use super::summary::{
    IterationReport, Summary, Termination, TerminationReason, Timings, UsedOptions,
};
use super::warm::OrderingCache;
use super::{evaluate_chi2, evaluate_chi2_within, SolverError};
use crate::factors::FactorEntry;
use crate::problem::{Gauge, Key, Problem, Values};

/// Optimises `problem.values` in place. `on_iteration` sees every iteration as it finishes and
/// may stop the solve there (`ControlFlow::Break`): the values are then those of the last accepted
/// step and the termination reason is [`TerminationReason::Interrupted`].
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
/// It may also stop after a step whose actual decrease matched the quadratic model's prediction
/// to within `function_tolerance × chi2`: the model was then accurate over the step, so the
/// step landed at the model's minimum and a further one cannot gain more than that tolerance.
/// This saves the confirming iteration a cold solve needs; the initialisation option is ignored.
/// `ordering` carries the elimination order between the re-solves of a growing problem.
pub fn optimize_warm(
    problem: &mut Problem,
    options: &SolverOptions,
    on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
    ordering: &mut OrderingCache,
) -> Result<Summary, SolverError> {
    let options = SolverOptions {
        initialization: Initialization::None,
        ..options.clone()
    };
    optimize_from(problem, &options, on_iteration, Some(ordering), &Unlimited)
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
    let initial_chi2 = evaluate_chi2(problem.factors(), &problem.values)?;
    if !initial_chi2.is_finite() {
        return Err(SolverError::NonFiniteInitialCost);
    }

    // One fill-reducing order of the variable graph serves the initialisation and the solve;
    // with a Schur complement the eliminated variables come first.
    let schur_plan = schur::plan(
        problem.factors(),
        &problem.values,
        &fixed,
        &problem.eliminate,
        options.linear_solver,
    );
    let ordering = match (&schur_plan, cache) {
        (Some(plan), _) => plan.ordering.clone(),
        (None, Some(cache)) => cache.ordering(problem.factors(), &fixed),
        (None, None) => BlockOrdering::amd(free_adjacency(problem.factors(), &fixed)),
    };
    // The system's layout and symbolic factorisation only need the structure, so they come
    // before the initialisation: a solve too big for its memory budget is refused before any
    // numeric work.
    let layout = SystemLayout::with_ordering(problem.factors(), &problem.values, &fixed, &ordering);
    let chol = match &schur_plan {
        Some(plan) => LinearSolver::Schur(SchurSolver::new(&layout.pattern, plan)?),
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
    timings.preprocess_seconds = start.elapsed().as_secs_f64();

    let init_start = Instant::now();
    let (init_label, initialized_chi2) = run_initialization(
        problem,
        &fixed,
        &ordering,
        options.initialization,
        initial_chi2,
        budget,
    )?;
    timings.initialization_seconds = init_start.elapsed().as_secs_f64();

    let mut values = std::mem::take(&mut problem.values);
    let outcome = iterate(
        &mut values,
        problem.factors(),
        &layout,
        chol,
        timings,
        options,
        on_iteration,
        warm,
        budget,
    );
    problem.values = values;
    let run = outcome?;
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

/// What a finished iteration loop hands back.
pub(super) struct Run {
    chi2: f64,
    termination: Termination,
    log: Vec<IterationReport>,
    timings: Timings,
    factorization: &'static str,
    factor_nnz: usize,
    linear_solver: &'static str,
    ordering: &'static str,
    schur: Option<SchurReport>,
}

/// Facts about the solve that the iteration loop does not know.
pub(super) struct Context {
    pub start: Instant,
    pub initialization: String,
    pub gauge_fixed: Vec<Key>,
    pub initial_chi2: f64,
    pub initialized_chi2: Option<f64>,
    pub region: Option<usize>,
}

#[allow(clippy::too_many_arguments)]
pub(super) fn iterate<E: Borrow<FactorEntry>>(
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
    let n = layout.n();
    let cost = chol.factor_flops().map(|flops| FactorCost {
        flops,
        measured_rate: None,
    });
    let mut solver = Iterations {
        layout,
        scratch: Scratch::new(layout),
        h: vec![0.0; layout.pattern.nnz()],
        damped: vec![
            0.0;
            if chol.shifts_in_place() {
                n
            } else {
                layout.pattern.nnz()
            }
        ],
        b: vec![0.0; n],
        delta: vec![0.0; n],
        work: vec![0.0; n],
        product: vec![0.0; n],
        trial: values.clone(),
        chol,
        timings,
        log: Vec::new(),
        warm,
        budget,
        cost,
    };
    let (chi2, termination) = solver.run(factors, values, options, on_iteration)?;
    Ok(Run {
        chi2,
        termination,
        factorization: solver.chol.factorization(),
        factor_nnz: solver.chol.factor_nnz(),
        linear_solver: solver.chol.label(),
        ordering: solver.chol.ordering(),
        schur: solver.chol.schur_report(),
        log: solver.log,
        timings: solver.timings,
    })
}

impl Run {
    pub(super) fn summary<E: Borrow<FactorEntry>>(
        self,
        options: &SolverOptions,
        layout: &SystemLayout,
        factors: &[E],
        values: &Values,
        context: Context,
    ) -> Summary {
        let successful = self.log.iter().filter(|r| r.accepted).count();
        let iterations = self.log.len();
        Summary {
            method: options.method.name().into(),
            given_options: options.clone(),
            used: UsedOptions {
                method: options.method.name().into(),
                linear_solver: self.linear_solver.into(),
                factorization: self.factorization.into(),
                ordering: self.ordering.into(),
                threads: 1,
                initialization: context.initialization,
                gauge_fixed: context.gauge_fixed,
                schur: self.schur,
                region_variables: context.region,
            },
            num_variables: values.len(),
            num_free_variables: layout.var_at.len(),
            num_factors: factors.len(),
            num_residuals: factors
                .iter()
                .map(|f| f.borrow().factor.residual_dim())
                .sum(),
            num_parameters: layout.n(),
            jacobian_nnz_blocks: factors.iter().map(|f| f.borrow().factor.keys().len()).sum(),
            hessian_nnz: layout.pattern.nnz(),
            factor_nnz: self.factor_nnz,
            initial_chi2: context.initial_chi2,
            initialized_chi2: context.initialized_chi2,
            final_chi2: self.chi2,
            iterations,
            successful_steps: successful,
            unsuccessful_steps: iterations - successful,
            converged: self.termination.converged(),
            termination: self.termination,
            solve_seconds: context.start.elapsed().as_secs_f64(),
            timings: self.timings,
            iteration_log: self.log,
        }
    }
}

struct Iterations<'a> {
    layout: &'a SystemLayout,
    scratch: Scratch,
    h: Vec<f64>,
    damped: Vec<f64>,
    b: Vec<f64>,
    delta: Vec<f64>,
    /// Dogleg: the Gauss-Newton step, and a product H·v.
    work: Vec<f64>,
    product: Vec<f64>,
    trial: Values,
    chol: LinearSolver,
    timings: Timings,
    log: Vec<IterationReport>,
    /// Started near the optimum: see [`optimize_warm`].
    warm: bool,
    budget: &'a dyn Budget,
    /// What one factorisation costs, to not start one the budget has no time left for
    /// (`None`: not known for this linear solver).
    cost: Option<FactorCost>,
}

fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0f64, |m, x| m.max(x.abs()))
}

pub(super) fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Per-iteration times of the linear algebra, for the report.
#[derive(Default, Clone, Copy)]
struct StepTimes {
    linearize: f64,
    factorize: f64,
    solve: f64,
}

impl Iterations<'_> {
    fn indeterminate(&self, values: &Values, e: NotPositiveDefinite) -> SolverError {
        SolverError::IndeterminateSystem {
            keys: vec![self.layout.key_at_row(values, e.row)],
        }
    }

    fn linearize_at<E: Borrow<FactorEntry>>(
        &mut self,
        factors: &[E],
        values: &Values,
        times: &mut StepTimes,
    ) -> Result<ControlFlow<(), f64>, SolverError> {
        let t = Instant::now();
        let chi2 = linearize_within(
            factors,
            values,
            self.layout,
            &mut self.scratch,
            &mut self.h,
            &mut self.b,
            self.budget,
        )?;
        let s = t.elapsed().as_secs_f64();
        self.timings.linearize_seconds += s;
        times.linearize += s;
        Ok(chi2)
    }

    /// chi2 at `values ⊕ delta`, leaving that point in `self.trial`.
    fn evaluate_trial<E: Borrow<FactorEntry>>(
        &mut self,
        factors: &[E],
        values: &Values,
    ) -> Result<ControlFlow<(), f64>, SolverError> {
        let t = Instant::now();
        self.trial.assign_from(values);
        self.layout.retract(&mut self.trial, &self.delta);
        let chi2 = evaluate_chi2_within(factors, &self.trial, self.budget)?;
        self.timings.evaluate_seconds += t.elapsed().as_secs_f64();
        Ok(chi2.map_continue(|chi2| {
            if chi2.is_finite() {
                chi2
            } else {
                f64::INFINITY
            }
        }))
    }

    /// D's entry for scalar column `c`: the diagonal of H, clamped as Ceres does so that a zero
    /// or huge curvature still gives a usable damping.
    fn damping_diagonal(&self, c: usize) -> f64 {
        self.h[self.layout.pattern.diagonal_index(c)].clamp(1e-6, 1e32)
    }

    /// Factorises H + λD (H itself when λ = 0) and solves for `delta` = (H + λD)⁻¹ b.
    /// `Break`: the budget stopped the solve first (a factorisation is one uninterruptible call:
    /// it is not started when its predicted time exceeds the time left).
    fn solve_damped(
        &mut self,
        lambda: f64,
        times: &mut StepTimes,
    ) -> Result<ControlFlow<()>, NotPositiveDefinite> {
        if self.budget.checkpoint().is_break()
            || self.cost.is_some_and(|cost| !cost.fits(self.budget))
        {
            return Ok(ControlFlow::Break(()));
        }
        let pattern = &self.layout.pattern;
        let t = Instant::now();
        let result = if lambda > 0.0 && self.chol.shifts_in_place() {
            for c in 0..pattern.n {
                self.damped[c] = lambda * self.damping_diagonal(c);
            }
            self.chol
                .factorize_shifted(pattern, &self.h, &self.damped, self.budget)
        } else if lambda > 0.0 {
            self.damped.copy_from_slice(&self.h);
            for c in 0..pattern.n {
                self.damped[pattern.diagonal_index(c)] += lambda * self.damping_diagonal(c);
            }
            self.chol.factorize(pattern, &self.damped, self.budget)
        } else {
            self.chol.factorize(pattern, &self.h, self.budget)
        };
        let took = t.elapsed();
        if let Some(cost) = &mut self.cost {
            cost.measure(took);
        }
        let s = took.as_secs_f64();
        self.timings.factorize_seconds += s;
        times.factorize += s;
        if result?.is_break() {
            return Ok(ControlFlow::Break(()));
        }
        let t = Instant::now();
        self.delta.copy_from_slice(&self.b);
        self.chol.solve_in_place(&mut self.delta);
        let s = t.elapsed().as_secs_f64();
        self.timings.linear_solve_seconds += s;
        times.solve += s;
        Ok(ControlFlow::Continue(()))
    }

    /// λ·ΔᵀDΔ.
    fn damping_term(&self, lambda: f64) -> f64 {
        (0..self.layout.n())
            .map(|c| lambda * self.damping_diagonal(c) * self.delta[c] * self.delta[c])
            .sum()
    }

    fn run<E: Borrow<FactorEntry>>(
        &mut self,
        factors: &[E],
        values: &mut Values,
        options: &SolverOptions,
        on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
    ) -> Result<(f64, Termination), SolverError> {
        let mut times = StepTimes::default();
        let mut chi2 = match self.linearize_at(factors, values, &mut times)? {
            ControlFlow::Continue(chi2) => chi2,
            // Stopped before anything was computed: the report still needs the start's chi2.
            ControlFlow::Break(()) => return Ok((evaluate_chi2(factors, values)?, stopped(0))),
        };
        if self.layout.n() == 0 || factors.is_empty() {
            return Ok((
                chi2,
                termination(TerminationReason::Trivial, 0.0, 0.0, "nothing to optimise"),
            ));
        }
        // LM tries an undamped (Gauss-Newton) step first unless told otherwise; damping starts at
        // the first rejection.
        let mut lambda = if options.method == Method::LevenbergMarquardt && options.damp_first_step
        {
            options.initial_lambda
        } else {
            0.0
        };
        let mut nu = 2.0;
        let mut radius = options.initial_trust_radius;
        let mut have_gn_step = false;
        for iteration in 1..=options.max_iterations {
            let gradient = max_abs(&self.b);
            if options.gradient_tolerance > 0.0 && gradient <= options.gradient_tolerance {
                return Ok((
                    chi2,
                    termination(
                        TerminationReason::GradientTolerance,
                        gradient,
                        options.gradient_tolerance,
                        &format!(
                            "gradient tolerance reached: |g|inf = {gradient:.3e} <= {:.3e}",
                            options.gradient_tolerance
                        ),
                    ),
                ));
            }
            // Model decrease L(0) − L(Δ) of the step, for LM/Dogleg's gain ratio and the warm stop.
            let mut predicted = f64::NAN;
            // Inside an iteration the budget is checked before each factorisation and every few
            // thousand factors; stopping there keeps the last accepted values.
            macro_rules! or_stop {
                ($flow:expr) => {
                    match $flow {
                        ControlFlow::Continue(v) => v,
                        ControlFlow::Break(()) => return Ok((chi2, stopped(iteration))),
                    }
                };
            }
            let (accepted, trial_chi2) = match options.method {
                Method::GaussNewton => {
                    or_stop!(self
                        .solve_damped(0.0, &mut times)
                        .map_err(|e| self.indeterminate(values, e))?);
                    predicted = dot(&self.delta, &self.b);
                    let trial = or_stop!(self.evaluate_trial(factors, values)?);
                    if !trial.is_finite() {
                        return Err(SolverError::Diverged { iteration });
                    }
                    (true, trial)
                }
                Method::LevenbergMarquardt => match self.solve_damped(lambda, &mut times) {
                    Ok(ControlFlow::Break(())) => return Ok((chi2, stopped(iteration))),
                    Ok(ControlFlow::Continue(())) => {
                        predicted = dot(&self.delta, &self.b) + self.damping_term(lambda);
                        let trial = or_stop!(self.evaluate_trial(factors, values)?);
                        let rho = (chi2 - trial) / predicted;
                        if trial.is_finite() && rho > 0.0 && predicted > 0.0 {
                            lambda *= (1.0f64 / 3.0).max(1.0 - (2.0 * rho - 1.0).powi(3));
                            if lambda < LAMBDA_SNAP_TO_ZERO {
                                lambda = 0.0;
                            }
                            nu = 2.0;
                            (true, trial)
                        } else {
                            lambda = increase_damping(lambda, &mut nu, options.initial_lambda);
                            (false, trial)
                        }
                    }
                    Err(_) => {
                        // Not positive definite at this damping: damp more.
                        lambda = increase_damping(lambda, &mut nu, options.initial_lambda);
                        self.delta.fill(0.0);
                        (false, f64::INFINITY)
                    }
                },
                Method::Dogleg => {
                    if !have_gn_step {
                        or_stop!(self.dogleg_gauss_newton_step(values, &mut times)?);
                        have_gn_step = true;
                    }
                    predicted = self.dogleg_step(radius);
                    let trial = or_stop!(self.evaluate_trial(factors, values)?);
                    let rho = (chi2 - trial) / predicted;
                    let step = self.delta.iter().map(|v| v * v).sum::<f64>().sqrt();
                    if rho > 0.75 {
                        radius = radius.max(3.0 * step);
                    } else if rho < 0.25 || !trial.is_finite() {
                        radius = 0.5 * step.min(radius);
                    }
                    (trial.is_finite() && rho > 0.0 && predicted > 0.0, trial)
                }
            };
            let step_norm = max_abs(&self.delta);
            let previous = chi2;
            if accepted {
                std::mem::swap(values, &mut self.trial);
                have_gn_step = false;
            }
            let relative_decrease = if accepted {
                (previous - trial_chi2) / previous.max(f64::MIN_POSITIVE)
            } else {
                0.0
            };
            let stop = if !accepted {
                None
            } else if options.function_tolerance > 0.0
                && relative_decrease.abs() <= options.function_tolerance
            {
                Some(termination(
                    TerminationReason::FunctionTolerance,
                    relative_decrease,
                    options.function_tolerance,
                    &format!(
                        "function tolerance reached: relative decrease {relative_decrease:.3e} <= {:.3e}",
                        options.function_tolerance
                    ),
                ))
            } else if self.warm
                && options.function_tolerance > 0.0
                && ((previous - trial_chi2) - predicted).abs()
                    <= options.function_tolerance * trial_chi2
            {
                let mismatch = ((previous - trial_chi2) - predicted).abs() / trial_chi2;
                Some(termination(
                    TerminationReason::FunctionTolerance,
                    mismatch,
                    options.function_tolerance,
                    &format!(
                        "function tolerance reached: the step's decrease matched the quadratic model to {mismatch:.3e} of chi2 <= {:.3e} (warm start)",
                        options.function_tolerance
                    ),
                ))
            } else if options.parameter_tolerance > 0.0 && step_norm <= options.parameter_tolerance
            {
                Some(termination(
                    TerminationReason::ParameterTolerance,
                    step_norm,
                    options.parameter_tolerance,
                    &format!(
                        "parameter tolerance reached: |dx|inf = {step_norm:.3e} <= {:.3e}",
                        options.parameter_tolerance
                    ),
                ))
            } else {
                None
            };
            // Relinearise at the new point, unless this step ends the solve: then its chi2 (already
            // evaluated) is all that is needed. A budget that stops the relinearisation ends the
            // solve at the accepted point after this iteration's report.
            let mut budget_stop = None;
            if accepted {
                chi2 = match stop {
                    Some(_) => trial_chi2,
                    None => match self.linearize_at(factors, values, &mut times)? {
                        ControlFlow::Continue(chi2) => chi2,
                        ControlFlow::Break(()) => {
                            budget_stop = Some(stopped(iteration));
                            trial_chi2
                        }
                    },
                };
            }
            let stop = stop.or(budget_stop);
            let report = IterationReport {
                iteration,
                chi2,
                trial_chi2,
                relative_decrease,
                gradient_max_norm: gradient,
                step_norm,
                lambda: (options.method == Method::LevenbergMarquardt).then_some(lambda),
                trust_radius: (options.method == Method::Dogleg).then_some(radius),
                accepted,
                linearize_seconds: times.linearize,
                factorize_seconds: times.factorize,
                solve_seconds: times.solve,
            };
            times = StepTimes::default();
            let control = on_iteration(&report);
            self.log.push(report);
            if let Some(stop) = stop {
                return Ok((chi2, stop));
            }
            if control.is_break() {
                return Ok((
                    chi2,
                    termination(
                        TerminationReason::Interrupted,
                        iteration as f64,
                        0.0,
                        "interrupted by the caller after this iteration",
                    ),
                ));
            }
            if lambda > 1e16 || radius < 1e-16 {
                let (value, threshold) = if lambda > 1e16 {
                    (lambda, 1e16)
                } else {
                    (radius, 1e-16)
                };
                return Ok((
                    chi2,
                    termination(
                        TerminationReason::NoProgress,
                        value,
                        threshold,
                        "no acceptable step: damping / trust region out of range",
                    ),
                ));
            }
        }
        let n = options.max_iterations as f64;
        Ok((
            chi2,
            termination(
                TerminationReason::MaxIterations,
                n,
                n,
                &format!(
                    "maximum number of iterations reached ({})",
                    options.max_iterations
                ),
            ),
        ))
    }

    /// Gauss-Newton step for Dogleg into `work`; a singular H gets the smallest damping that works.
    fn dogleg_gauss_newton_step(
        &mut self,
        values: &Values,
        times: &mut StepTimes,
    ) -> Result<ControlFlow<()>, SolverError> {
        let mut mu = 0.0;
        loop {
            match self.solve_damped(mu, times) {
                Ok(ControlFlow::Break(())) => return Ok(ControlFlow::Break(())),
                Ok(ControlFlow::Continue(())) => break,
                Err(e) if mu > 1e8 => return Err(self.indeterminate(values, e)),
                Err(_) => mu = if mu == 0.0 { 1e-10 } else { mu * 100.0 },
            }
        }
        std::mem::swap(&mut self.work, &mut self.delta);
        Ok(ControlFlow::Continue(()))
    }

    /// Powell's dogleg inside `radius` from the GN step (in `work`) and the Cauchy point; writes
    /// the step to `delta` and returns the model decrease 2Δᵀb − ΔᵀHΔ.
    fn dogleg_step(&mut self, radius: f64) -> f64 {
        let pattern = &self.layout.pattern;
        let gn_norm = dot(&self.work, &self.work).sqrt();
        if gn_norm <= radius {
            self.delta.copy_from_slice(&self.work);
        } else {
            symmetric_multiply(pattern, &self.h, &self.b, &mut self.product);
            let bb = dot(&self.b, &self.b);
            let alpha = bb / dot(&self.b, &self.product).max(f64::MIN_POSITIVE);
            let sd_norm = alpha * bb.sqrt();
            if sd_norm >= radius {
                let s = radius / bb.sqrt();
                for (d, b) in self.delta.iter_mut().zip(&self.b) {
                    *d = s * b;
                }
            } else {
                // h = a + β (g − a), |h| = radius, a = α b (Cauchy point), g = GN step.
                let (mut aa, mut ad, mut dd) = (0.0, 0.0, 0.0);
                for (g, b) in self.work.iter().zip(&self.b) {
                    let (a, diff) = (alpha * b, g - alpha * b);
                    (aa, ad, dd) = (aa + a * a, ad + a * diff, dd + diff * diff);
                }
                let c = aa - radius * radius;
                let beta = (-ad + (ad * ad - dd * c).max(0.0).sqrt()) / dd.max(f64::MIN_POSITIVE);
                for ((d, g), b) in self.delta.iter_mut().zip(&self.work).zip(&self.b) {
                    *d = alpha * b + beta * (g - alpha * b);
                }
            }
        }
        symmetric_multiply(pattern, &self.h, &self.delta, &mut self.product);
        2.0 * dot(&self.delta, &self.b) - dot(&self.delta, &self.product)
    }
}

/// Below this, LM damping is dropped altogether: on pose graphs H is so ill-conditioned that even
/// λ = 1e-9·diag(H) slows the long-wavelength modes, and a full Gauss-Newton step is what converges.
const LAMBDA_SNAP_TO_ZERO: f64 = 1e-9;

/// Nielsen's rejection rule λ ← λν, ν ← 2ν, starting from `restart` when λ was 0.
fn increase_damping(lambda: f64, nu: &mut f64, restart: f64) -> f64 {
    if lambda == 0.0 {
        *nu = 2.0;
        return restart;
    }
    let next = lambda * *nu;
    *nu *= 2.0;
    next
}

/// The solve's budget stopped it inside iteration `iteration` (0: before the first).
fn stopped(iteration: usize) -> Termination {
    termination(
        TerminationReason::Interrupted,
        iteration as f64,
        0.0,
        &format!("interrupted by the solve's budget (time limit, cancellation or shutdown) during iteration {iteration}; the estimate is the last accepted step"),
    )
}

fn termination(
    reason: TerminationReason,
    value: f64,
    threshold: f64,
    message: &str,
) -> Termination {
    Termination {
        reason,
        value,
        threshold,
        message: message.to_string(),
    }
}
