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
use super::linearize::{gradient_within, linearize_within, Scratch, SystemLayout};
use super::options::{Method, SolverOptions};
use super::stopping::{accepted_step_stop, stopped, termination};
use super::summary::{IterationReport, Run, Termination, TerminationReason, Timings};
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
    /// `h` is not of the current point (only `b` was relinearised, for a chord step).
    pub(super) hessian_stale: bool,
}

/// A chord step is tried only after a step that lowered chi2 by less than this fraction:
/// Gauss-Newton is then in its fast local phase and H barely changes. After larger steps the
/// old factorisation was never good enough on the graphs measured (M3500's first step: 21%),
/// and trying it costs a solve.
const CHORD_AFTER_DECREASE: f64 = 0.1;

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

impl<'a> Iterations<'a> {
    /// The loop state for solving over `layout` with `chol`, starting from values shaped like
    /// `values`.
    pub(super) fn new(
        layout: &'a SystemLayout,
        chol: LinearSolver,
        timings: Timings,
        values: &Values,
        warm: bool,
        budget: &'a dyn Budget,
    ) -> Self {
        Self::with_trial(layout, chol, timings, values.clone(), warm, budget)
    }

    /// [`Iterations::new`] with the buffer for trial points given: any values with the same
    /// variables as the ones the loop will run on (a copy costs an allocation per variable).
    pub(super) fn with_trial(
        layout: &'a SystemLayout,
        chol: LinearSolver,
        timings: Timings,
        trial: Values,
        warm: bool,
        budget: &'a dyn Budget,
    ) -> Self {
        let n = layout.n();
        let cost = chol.factor_flops().map(|flops| FactorCost {
            flops,
            measured_rate: None,
        });
        let damped = if chol.shifts_in_place() {
            n
        } else {
            layout.pattern.nnz()
        };
        Self {
            layout,
            scratch: Scratch::new(layout),
            h: vec![0.0; layout.pattern.nnz()],
            damped: vec![0.0; damped],
            b: vec![0.0; n],
            delta: vec![0.0; n],
            work: vec![0.0; n],
            product: vec![0.0; n],
            trial,
            chol,
            timings,
            log: Vec::new(),
            warm,
            budget,
            cost,
            hessian_stale: false,
        }
    }

    /// What the loop leaves for the Summary, once it ended with `chi2` and `termination`.
    pub(super) fn finish(self, chi2: f64, termination: Termination) -> Run {
        Run {
            chi2,
            termination,
            factorization: self.chol.factorization(),
            factor_nnz: self.chol.factor_nnz(),
            linear_solver: self.chol.label(),
            ordering: self.chol.ordering(),
            schur: self.chol.schur_report(),
            log: self.log,
            timings: self.timings,
        }
    }

    pub(super) fn indeterminate(&self, values: &Values, e: NotPositiveDefinite) -> SolverError {
        SolverError::IndeterminateSystem {
            keys: vec![self.layout.key_at_row(values, e.row)],
        }
    }

    /// Linearises at `values` into H and b; returns chi2 there (`Break`: the budget stopped it).
    pub(super) fn linearize_at<E: Borrow<FactorEntry>>(
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
        self.hessian_stale = false;
        Ok(chi2)
    }

    /// [`Iterations::linearize_at`] for `b` and chi2 only; H stays that of the last point.
    fn gradient_at<E: Borrow<FactorEntry>>(
        &mut self,
        factors: &[E],
        values: &Values,
        times: &mut StepTimes,
    ) -> Result<ControlFlow<(), f64>, SolverError> {
        let t = Instant::now();
        let chi2 = gradient_within(
            factors,
            values,
            self.layout,
            &mut self.scratch,
            &mut self.b,
            self.budget,
        )?;
        let s = t.elapsed().as_secs_f64();
        self.timings.linearize_seconds += s;
        times.linearize += s;
        self.hessian_stale = true;
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

    /// A Gauss-Newton step at the current point with the previous point's factorisation (a
    /// chord step): `delta = H_prev⁻¹ b`. Worth taking instead of a fresh factorisation when its
    /// predicted decrease `deltaᵀb` is already within the function tolerance of `chi2`: the
    /// solve is then about to stop, and that step only has to be small and downhill, which the
    /// trial evaluation checks (the stopping test is still on the actual decrease). Returns
    /// whether `delta` holds such a step; near the optimum H barely changes between
    /// iterations, so this saves the last factorisation of a solve.
    fn chord_step(&mut self, options: &SolverOptions, chi2: f64, times: &mut StepTimes) -> bool {
        let t = Instant::now();
        self.delta.copy_from_slice(&self.b);
        self.chol.solve_in_place(&mut self.delta);
        let s = t.elapsed().as_secs_f64();
        self.timings.linear_solve_seconds += s;
        times.solve += s;
        let predicted = dot(&self.delta, &self.b);
        predicted >= 0.0 && predicted <= options.function_tolerance * chi2
    }

    pub(super) fn run<E: Borrow<FactorEntry>>(
        &mut self,
        factors: &[E],
        values: &mut Values,
        options: &SolverOptions,
        on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
    ) -> Result<(f64, Termination), SolverError> {
        let mut times = StepTimes::default();
        let first = self.linearize_at(factors, values, &mut times)?;
        self.run_linearized(factors, values, options, on_iteration, first, times)
    }

    /// [`Iterations::run`] after the caller linearised at `values` itself (`first`, with the
    /// time it took in `times`).
    pub(super) fn run_linearized<E: Borrow<FactorEntry>>(
        &mut self,
        factors: &[E],
        values: &mut Values,
        options: &SolverOptions,
        on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
        first: ControlFlow<(), f64>,
        mut times: StepTimes,
    ) -> Result<(f64, Termination), SolverError> {
        let mut chi2 = match first {
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
        // The factorisation in hand is of the last point's H, whose (fresh) step was accepted.
        let mut chord_allowed = false;
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
            // Gauss-Newton: whether this iteration's step reuses the last factorisation.
            let mut chord = false;
            let (accepted, trial_chi2) = match options.method {
                Method::GaussNewton => {
                    chord = chord_allowed && self.chord_step(options, chi2, &mut times);
                    if !chord {
                        if self.hessian_stale {
                            or_stop!(self.linearize_at(factors, values, &mut times)?);
                        }
                        or_stop!(self
                            .solve_damped(0.0, &mut times)
                            .map_err(|e| self.indeterminate(values, e))?);
                    }
                    predicted = dot(&self.delta, &self.b);
                    let trial = or_stop!(self.evaluate_trial(factors, values)?);
                    // Not at most chi2 (NaN included).
                    let worse = !matches!(
                        trial.partial_cmp(&chi2),
                        Some(std::cmp::Ordering::Less | std::cmp::Ordering::Equal)
                    );
                    if chord && worse {
                        // The old factorisation was not good enough here: discard the step, and
                        // factorise at this point next.
                        (false, trial)
                    } else if !trial.is_finite() {
                        return Err(SolverError::Diverged { iteration });
                    } else {
                        (true, trial)
                    }
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
            let step_two_norm = self.delta.iter().map(|v| v * v).sum::<f64>().sqrt();
            let gain_ratio = Some((chi2 - trial_chi2) / predicted)
                .filter(|r| r.is_finite())
                .unwrap_or(0.0);
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
            chord_allowed = accepted
                && !chord
                && !self.warm
                && options.method == Method::GaussNewton
                && options.function_tolerance > 0.0
                && relative_decrease > 0.0
                && relative_decrease < CHORD_AFTER_DECREASE;
            let mut budget_stop = None;
            if accepted {
                let relinearized = match stop {
                    Some(_) => None,
                    // A chord step comes next: it needs only the gradient (H follows if the
                    // chord step is not taken after all).
                    None if chord_allowed => Some(self.gradient_at(factors, values, &mut times)?),
                    None => Some(self.linearize_at(factors, values, &mut times)?),
                };
                chi2 = match relinearized {
                    None => trial_chi2,
                    Some(flow) => match flow {
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
                step_two_norm,
                gain_ratio,
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

#[cfg(test)]
mod tests {
    use nalgebra::DMatrix;

    use crate::factors::BetweenSe2;
    use crate::geometry::Se2;
    use crate::problem::Problem;
    use crate::solver::{optimize, SolverOptions};

    /// A noisy pose graph: a circle of poses with odometry and loop closures, measurements
    /// perturbed by a fixed pseudo-random sequence, odometry-integrated start.
    fn noisy_circle() -> Problem {
        let mut state = 12345u64;
        let mut noise = |scale: f64| {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * scale
        };
        let n = 60;
        let truth: Vec<Se2> = (0..n)
            .map(|k| {
                let a = k as f64 * 2.0 * std::f64::consts::PI / n as f64;
                Se2::new(
                    10.0 * a.cos(),
                    10.0 * a.sin(),
                    a + std::f64::consts::FRAC_PI_2,
                )
            })
            .collect();
        let mut edges = Vec::new();
        for k in 0..n {
            edges.push((k, (k + 1) % n));
            if k % 7 == 0 {
                edges.push((k, (k + n / 2) % n));
            }
        }
        let information =
            DMatrix::from_row_slice(3, 3, &[100.0, 5.0, 0.0, 5.0, 100.0, 0.0, 0.0, 0.0, 900.0]);
        let mut problem = Problem::new();
        let mut measured = Vec::new();
        for &(i, j) in &edges {
            let z = truth[i].between(&truth[j]);
            measured.push(Se2::new(
                z.x + noise(0.2),
                z.y + noise(0.2),
                z.theta + noise(0.05),
            ));
        }
        // Start: integrated odometry, so the loop closures start far off.
        let mut pose = truth[0];
        for k in 0..n {
            problem.add_variable(k as u64, Box::new(pose)).unwrap();
            pose =
                pose.compose(&measured[edges.iter().position(|&e| e == (k, (k + 1) % n)).unwrap()]);
        }
        for (&(i, j), z) in edges.iter().zip(&measured) {
            let factor = BetweenSe2::new(i as u64, j as u64, *z);
            problem
                .add_factor(Box::new(factor), &information, None, "edge")
                .unwrap();
        }
        problem
    }

    /// Gauss-Newton's last step may reuse the previous factorisation (a chord step); the solve
    /// still stops on the actual decrease and ends at the optimum a fully converged solve finds.
    #[test]
    fn the_chord_step_ends_at_the_converged_optimum() {
        let mut problem = noisy_circle();
        let options = SolverOptions::default();
        let summary = optimize(&mut problem, &options, &mut |_| {
            std::ops::ControlFlow::Continue(())
        })
        .unwrap();
        assert!(summary.converged, "{}", summary.termination.message);
        let chord_steps = summary
            .iteration_log
            .iter()
            .filter(|r| r.accepted && r.factorize_seconds == 0.0)
            .count();
        assert_eq!(
            chord_steps, 1,
            "the last step reuses the factorisation: {:?}",
            summary.iteration_log
        );

        let mut reference = noisy_circle();
        let tight = SolverOptions {
            function_tolerance: 0.0,
            max_iterations: 12,
            ..SolverOptions::default()
        };
        let converged = optimize(&mut reference, &tight, &mut |_| {
            std::ops::ControlFlow::Continue(())
        })
        .unwrap();
        let gap = (summary.final_chi2 - converged.final_chi2) / converged.final_chi2;
        assert!(
            gap.abs() <= 1e-7,
            "chi2 {} vs converged {}",
            summary.final_chi2,
            converged.final_chi2
        );
    }
}
