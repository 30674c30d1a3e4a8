//! The step strategies behind the one iteration loop of [`super::iterations`], split the way
//! Ceres splits its `TrustRegionStrategy`: a strategy **computes a step** into the loop's `delta`
//! (with the model decrease L(0) − L(Δ) it predicts), **judges** the trial point the loop
//! evaluated there (accepting or rejecting it, and updating its own λ or radius), and says after
//! each iteration what the next linearisation needs. The loop itself (gradient stop, trial
//! evaluation, convergence tests, relinearisation, reports, budget stops) is shared.
//!
//! - [`GaussNewton`] (`gauss_newton.rs`): undamped steps, reusing the last factorisation for a
//!   chord step near the optimum.
//! - [`LevenbergMarquardt`] (`damping.rs`): (H + λD)Δ = b with Nielsen's λ updates.
//! - [`Dogleg`] (`dogleg.rs`): Powell's dogleg inside a trust radius.

use std::borrow::Borrow;
use std::ops::ControlFlow;

use super::damping::LevenbergMarquardt;
use super::dogleg::Dogleg;
use super::gauss_newton::GaussNewton;
use super::iterations::{Iterations, StepTimes};
use super::options::{Method, SolverOptions};
use super::summary::Termination;
use super::SolverError;
use crate::problem::{FactorEntry, Values};

/// The method of one solve, with its state between iterations.
pub(super) enum Strategy {
    GaussNewton(GaussNewton),
    LevenbergMarquardt(LevenbergMarquardt),
    Dogleg(Dogleg),
}

/// What a strategy's step computation came to.
pub(super) enum Proposal {
    /// A step is in `delta`, with the model decrease it predicts; `undamped`: it is the
    /// quadratic model's minimum (a Gauss-Newton step, LM at λ = 0, a Dogleg step inside the
    /// trust radius), not a step shortened by damping or a trust region.
    Step { predicted: f64, undamped: bool },
    /// No step this iteration (LM's damped system was not positive definite: λ was raised and
    /// `delta` zeroed); the iteration counts as rejected without evaluating a trial.
    Skip,
}

impl Strategy {
    pub(super) fn new(options: &SolverOptions) -> Self {
        match options.method {
            Method::GaussNewton => Self::GaussNewton(GaussNewton::default()),
            Method::LevenbergMarquardt => {
                Self::LevenbergMarquardt(LevenbergMarquardt::new(options))
            }
            Method::Dogleg => Self::Dogleg(Dogleg::new(options)),
        }
    }

    /// Computes this iteration's step at `values` (chi2 `chi2`) into `it.delta`. `Break`: the
    /// budget stopped it.
    pub(super) fn compute_step<E: Borrow<FactorEntry> + Sync>(
        &mut self,
        it: &mut Iterations<'_>,
        factors: &[E],
        values: &Values,
        chi2: f64,
        options: &SolverOptions,
        times: &mut StepTimes,
    ) -> Result<ControlFlow<(), Proposal>, SolverError> {
        match self {
            Self::GaussNewton(gn) => gn.compute_step(it, factors, values, chi2, options, times),
            Self::LevenbergMarquardt(lm) => Ok(lm.compute_step(it, times)),
            Self::Dogleg(dl) => dl.compute_step(it, values, times),
        }
    }

    /// Whether the trial point (chi2 `trial`, reached by a step of 2-norm `step_two_norm` whose
    /// model predicted `predicted`) is accepted; updates λ or the radius. Gauss-Newton fails with
    /// [`SolverError::Diverged`] on a non-finite trial it cannot reject.
    pub(super) fn judge(
        &mut self,
        chi2: f64,
        trial: f64,
        predicted: f64,
        step_two_norm: f64,
        iteration: usize,
    ) -> Result<bool, SolverError> {
        match self {
            Self::GaussNewton(gn) => gn.judge(chi2, trial, iteration),
            Self::LevenbergMarquardt(lm) => Ok(lm.judge(chi2, trial, predicted)),
            Self::Dogleg(dl) => Ok(dl.judge(chi2, trial, predicted, step_two_norm)),
        }
    }

    /// After the iteration's step was accepted or rejected (and, if accepted, lowered chi2 by the
    /// fraction `relative_decrease`): returns whether the next point needs only the gradient
    /// (Gauss-Newton's chord step reuses the last H).
    pub(super) fn step_done(
        &mut self,
        accepted: bool,
        relative_decrease: f64,
        warm: bool,
        options: &SolverOptions,
    ) -> bool {
        match self {
            Self::GaussNewton(gn) => gn.step_done(accepted, relative_decrease, warm, options),
            Self::LevenbergMarquardt(_) => false,
            Self::Dogleg(dl) => {
                dl.step_done(accepted);
                false
            }
        }
    }

    /// LM's damping, for the report.
    pub(super) fn lambda(&self) -> Option<f64> {
        match self {
            Self::LevenbergMarquardt(lm) => Some(lm.lambda),
            _ => None,
        }
    }

    /// Dogleg's trust radius, for the report.
    pub(super) fn radius(&self) -> Option<f64> {
        match self {
            Self::Dogleg(dl) => Some(dl.radius),
            _ => None,
        }
    }

    /// The solve ends without progress: λ grew or the radius shrank out of range.
    pub(super) fn out_of_range(&self) -> Option<Termination> {
        match self {
            Self::GaussNewton(_) => None,
            Self::LevenbergMarquardt(lm) => lm.out_of_range(),
            Self::Dogleg(dl) => dl.out_of_range(),
        }
    }
}
