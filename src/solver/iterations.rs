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
use super::linear::LinearSolver;
use super::linearize::{gradient_within, linearize_within, Scratch, SystemLayout};
use super::options::SolverOptions;
use super::stopping::{
    accepted_step_stop, gradient_stop, interrupted_by_caller, max_iterations, stopped, termination,
};
use super::strategy::{Proposal, Strategy};
use super::summary::{IterationReport, Run, Termination, TerminationReason, Timings};
use super::vector::{dot, max_abs};
use super::{evaluate_chi2, evaluate_chi2_threads, SolverError};
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

/// Per-iteration times of the linear algebra, for the report.
#[derive(Default, Clone, Copy)]
pub(super) struct StepTimes {
    pub(super) linearize: f64,
    pub(super) factorize: f64,
    pub(super) solve: f64,
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
            h: super::huge_pages::zeroed(layout.pattern.nnz()),
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
    pub(super) fn linearize_at<E: Borrow<FactorEntry> + Sync>(
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
    fn gradient_at<E: Borrow<FactorEntry> + Sync>(
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
    fn evaluate_trial<E: Borrow<FactorEntry> + Sync>(
        &mut self,
        factors: &[E],
        values: &Values,
    ) -> Result<ControlFlow<(), f64>, SolverError> {
        let t = Instant::now();
        self.trial.assign_from(values);
        self.layout.retract(&mut self.trial, &self.delta);
        let threads = self.layout.threads();
        let chi2 = evaluate_chi2_threads(factors, &self.trial, self.budget, threads)?;
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
        self.solve_with_factor(times);
        Ok(ControlFlow::Continue(()))
    }

    /// `delta` = (the factorised matrix)⁻¹ `b`, with the factorisation in hand.
    pub(super) fn solve_with_factor(&mut self, times: &mut StepTimes) {
        let t = Instant::now();
        self.delta.copy_from_slice(&self.b);
        let (pattern, h) = (&self.layout.pattern, &self.h);
        self.chol.solve_in_place(pattern, h, &mut self.delta);
        let s = t.elapsed().as_secs_f64();
        self.timings.linear_solve_seconds += s;
        times.solve += s;
    }

    pub(super) fn run<E: Borrow<FactorEntry> + Sync>(
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
    pub(super) fn run_linearized<E: Borrow<FactorEntry> + Sync>(
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
        let mut strategy = Strategy::new(options);
        for iteration in 1..=options.max_iterations {
            let gradient = max_abs(&self.b);
            if let Some(end) = gradient_stop(options, gradient) {
                return Ok((chi2, end));
            }
            // A tenth of the decrease the function tolerance calls converged.
            self.chol
                .set_negligible_decrease(0.1 * options.function_tolerance * chi2);
            // Inside an iteration the budget is checked before each factorisation and every few
            // thousand factors; stopping there keeps the last accepted values.
            let step = match self.take_step(
                &mut strategy,
                factors,
                values,
                options,
                chi2,
                iteration,
                &mut times,
            )? {
                ControlFlow::Continue(step) => step,
                ControlFlow::Break(()) => return Ok((chi2, stopped(iteration))),
            };
            let previous = chi2;
            let (now, stop) = self.advance(
                &mut strategy,
                factors,
                values,
                options,
                &step,
                previous,
                iteration,
                &mut times,
            )?;
            chi2 = now;
            let report = step.report(iteration, previous, chi2, gradient, &strategy, &times);
            times = StepTimes::default();
            let control = on_iteration(&report);
            self.log.push(report);
            if let Some(stop) = stop {
                return Ok((chi2, stop));
            }
            if control.is_break() {
                return Ok((chi2, interrupted_by_caller(iteration)));
            }
            if let Some(end) = strategy.out_of_range() {
                return Ok((chi2, end));
            }
        }
        Ok((chi2, max_iterations(options)))
    }

    /// One step of `strategy` from `values` (chi2 `chi2`): computed, its trial point evaluated
    /// (left in `self.trial`) and judged. `Break`: the budget stopped it.
    #[allow(clippy::too_many_arguments)]
    fn take_step<E: Borrow<FactorEntry> + Sync>(
        &mut self,
        strategy: &mut Strategy,
        factors: &[E],
        values: &Values,
        options: &SolverOptions,
        chi2: f64,
        iteration: usize,
        times: &mut StepTimes,
    ) -> Result<ControlFlow<(), Step>, SolverError> {
        let proposal = match strategy.compute_step(self, factors, values, chi2, options, times)? {
            ControlFlow::Continue(proposal) => proposal,
            ControlFlow::Break(()) => return Ok(ControlFlow::Break(())),
        };
        let two_norm = dot(&self.delta, &self.delta).sqrt();
        let (trial_chi2, predicted, accepted, undamped) = match proposal {
            Proposal::Step {
                predicted,
                undamped,
            } => {
                let trial = match self.evaluate_trial(factors, values)? {
                    ControlFlow::Continue(trial) => trial,
                    ControlFlow::Break(()) => return Ok(ControlFlow::Break(())),
                };
                let accepted = strategy.judge(chi2, trial, predicted, two_norm, iteration)?;
                (trial, predicted, accepted, undamped)
            }
            Proposal::Skip => (f64::INFINITY, f64::NAN, false, false),
        };
        Ok(ControlFlow::Continue(Step {
            accepted,
            trial_chi2,
            predicted,
            undamped,
            norm: max_abs(&self.delta),
            two_norm,
        }))
    }

    /// Moves to the trial point of an accepted `step` and relinearises there, unless the step
    /// ends the solve (its chi2, already evaluated, is then all that is needed). Returns the chi2
    /// of the point the loop is at and, when the solve ends here, why: a convergence test, or a
    /// budget that stopped the relinearisation (the solve ends at the accepted point).
    #[allow(clippy::too_many_arguments)]
    fn advance<E: Borrow<FactorEntry> + Sync>(
        &mut self,
        strategy: &mut Strategy,
        factors: &[E],
        values: &mut Values,
        options: &SolverOptions,
        step: &Step,
        chi2: f64,
        iteration: usize,
        times: &mut StepTimes,
    ) -> Result<(f64, Option<Termination>), SolverError> {
        let relative_decrease = step.relative_decrease(chi2);
        let gradient_only =
            strategy.step_done(step.accepted, relative_decrease, self.warm, options);
        if !step.accepted {
            return Ok((chi2, None));
        }
        std::mem::swap(values, &mut self.trial);
        let stop = accepted_step_stop(
            options,
            // The model-match stop presumes the step reached the model's minimum.
            self.warm && step.undamped,
            relative_decrease,
            chi2,
            step.trial_chi2,
            step.predicted,
            step.norm,
        );
        if stop.is_some() {
            return Ok((step.trial_chi2, stop));
        }
        let relinearized = if gradient_only {
            self.gradient_at(factors, values, times)?
        } else {
            self.linearize_at(factors, values, times)?
        };
        Ok(match relinearized {
            ControlFlow::Continue(chi2) => (chi2, None),
            ControlFlow::Break(()) => (step.trial_chi2, Some(stopped(iteration))),
        })
    }
}

/// One iteration's step, as the report and the convergence tests see it.
struct Step {
    accepted: bool,
    trial_chi2: f64,
    /// The model decrease L(0) − L(Δ) (NaN: no step was computed).
    predicted: f64,
    /// The step is the model's minimum, not shortened by damping or a trust region.
    undamped: bool,
    /// max |Δᵢ| and ‖Δ‖₂.
    norm: f64,
    two_norm: f64,
}

impl Step {
    /// The fraction of `previous` the step removed (0 when rejected).
    fn relative_decrease(&self, previous: f64) -> f64 {
        if self.accepted {
            (previous - self.trial_chi2) / previous.max(f64::MIN_POSITIVE)
        } else {
            0.0
        }
    }

    /// The iteration's report: the step from chi2 `previous` to `chi2` (the point the loop is at
    /// now), the gradient it started from, the strategy's parameters and the linear algebra's
    /// times.
    fn report(
        &self,
        iteration: usize,
        previous: f64,
        chi2: f64,
        gradient: f64,
        strategy: &Strategy,
        times: &StepTimes,
    ) -> IterationReport {
        IterationReport {
            iteration,
            chi2,
            trial_chi2: self.trial_chi2,
            relative_decrease: self.relative_decrease(previous),
            gradient_max_norm: gradient,
            step_norm: self.norm,
            step_two_norm: self.two_norm,
            gain_ratio: self.gain_ratio(previous),
            lambda: strategy.lambda(),
            trust_radius: strategy.radius(),
            accepted: self.accepted,
            linearize_seconds: times.linearize,
            factorize_seconds: times.factorize,
            solve_seconds: times.solve,
        }
    }

    /// ρ = actual / predicted decrease (0 when not finite).
    fn gain_ratio(&self, previous: f64) -> f64 {
        Some((previous - self.trial_chi2) / self.predicted)
            .filter(|r| r.is_finite())
            .unwrap_or(0.0)
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
