//! The iteration loop shared by Gauss-Newton, Levenberg-Marquardt and Dogleg over one cached
//! linear system: linearise, solve the (damped) normal equations, evaluate the trial point,
//! accept or reject, report. The method-specific rules live in [`super::damping`] (LM's λ) and
//! [`super::dogleg`] (the trust-region step); when to stop is [`super::stopping`].
//!
//! Costs are chi2 = Σ ρ(‖r‖²) (no ½). For a step Δ solving (H + λD)Δ = b with b = −Jᵀr the
//! model decrease is L(0) − L(Δ) = 2Δᵀb − ΔᵀHΔ = Δᵀb + λΔᵀDΔ; the gain ratio
//! ρ = (F(x) − F(x ⊕ Δ)) / (L(0) − L(Δ)) decides acceptance and the next λ or radius.

use std::borrow::Borrow;
use std::ops::ControlFlow;
use std::time::Instant;

use super::budget::{Budget, FactorCost};
use super::cholesky::NotPositiveDefinite;
use super::damping::{decrease_damping, increase_damping};
use super::dogleg::update_trust_radius;
use super::linear::LinearSolver;
use super::linearize::{linearize_within, Scratch, SystemLayout};
use super::options::{Method, SolverOptions};
use super::stopping::{accepted_step_stop, stopped, termination};
use super::summary::{IterationReport, Termination, TerminationReason, Timings};
use super::{evaluate_chi2, evaluate_chi2_within, SolverError};
use crate::problem::FactorEntry;
use crate::problem::Values;

/// One solve's loop state: the cached linear system H, b and its work buffers. Its fields are
/// visible to the solver so that [`super::damping`] and [`super::dogleg`] can extend it with their
/// method-specific steps, and [`super::optimizer`] can build it.
pub(super) struct Iterations<'a> {
    pub(super) layout: &'a SystemLayout,
    pub(super) scratch: Scratch,
    pub(super) h: Vec<f64>,
    pub(super) damped: Vec<f64>,
    pub(super) b: Vec<f64>,
    pub(super) delta: Vec<f64>,
    /// Dogleg: the Gauss-Newton step, and a product H·v.
    pub(super) work: Vec<f64>,
    pub(super) product: Vec<f64>,
    pub(super) trial: Values,
    pub(super) chol: LinearSolver,
    pub(super) timings: Timings,
    pub(super) log: Vec<IterationReport>,
    /// Started near the optimum: see [`super::optimize_warm`].
    pub(super) warm: bool,
    pub(super) budget: &'a dyn Budget,
    /// What one factorisation costs, to not start one the budget has no time left for
    /// (`None`: not known for this linear solver).
    pub(super) cost: Option<FactorCost>,
}

fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0f64, |m, x| m.max(x.abs()))
}

pub(super) fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Per-iteration times of the linear algebra, for the report.
#[derive(Default, Clone, Copy)]
pub(super) struct StepTimes {
    linearize: f64,
    factorize: f64,
    solve: f64,
}

impl Iterations<'_> {
    pub(super) fn indeterminate(&self, values: &Values, e: NotPositiveDefinite) -> SolverError {
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

    /// Factorises H + λD (H itself when λ = 0) and solves for `delta` = (H + λD)⁻¹ b.
    /// `Break`: the budget stopped the solve first (a factorisation is one uninterruptible call:
    /// it is not started when its predicted time exceeds the time left).
    pub(super) fn solve_damped(
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

    pub(super) fn run<E: Borrow<FactorEntry>>(
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
                            lambda = decrease_damping(lambda, rho);
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
                    radius = update_trust_radius(radius, rho, step, trial.is_finite());
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
            let stop = if accepted {
                accepted_step_stop(
                    options,
                    self.warm,
                    relative_decrease,
                    previous,
                    trial_chi2,
                    predicted,
                    step_norm,
                )
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
}
