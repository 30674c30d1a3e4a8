//! Levenberg-Marquardt: the damped system H + λD with the scaling D = clamp(diag H), the
//! model-decrease term λΔᵀDΔ, and Nielsen's gain-ratio rules for shrinking λ after an accepted
//! step and growing it after a rejected one.

use std::ops::ControlFlow;

use super::iterations::{Iterations, StepTimes};
use super::options::SolverOptions;
use super::stopping::termination;
use super::strategy::Proposal;
use super::summary::{Termination, TerminationReason};
use super::vector::dot;

/// D's entries are diag(H) clamped to this range (as Ceres does), so that a zero or huge
/// curvature still gives a usable damping.
const DAMPING_DIAGONAL_RANGE: (f64, f64) = (1e-6, 1e32);

/// Below this, LM damping is dropped altogether: on pose graphs H is so ill-conditioned that even
/// λ = 1e-9·diag(H) slows the long-wavelength modes, and a full Gauss-Newton step is what converges.
const LAMBDA_SNAP_TO_ZERO: f64 = 1e-9;

/// Above this λ the steps are too short to matter: the solve ends without progress.
const MAX_LAMBDA: f64 = 1e16;

pub(super) struct LevenbergMarquardt {
    pub(super) lambda: f64,
    /// Nielsen's growth factor for λ after consecutive rejections.
    nu: f64,
    /// Where λ restarts after it had dropped to 0.
    initial_lambda: f64,
}

impl LevenbergMarquardt {
    /// An undamped (Gauss-Newton) first step unless `damp_first_step`: damping starts at the
    /// first rejection.
    pub(super) fn new(options: &SolverOptions) -> Self {
        Self {
            lambda: if options.damp_first_step {
                options.initial_lambda
            } else {
                0.0
            },
            nu: 2.0,
            initial_lambda: options.initial_lambda,
        }
    }

    pub(super) fn compute_step(
        &mut self,
        it: &mut Iterations<'_>,
        times: &mut StepTimes,
    ) -> ControlFlow<(), Proposal> {
        match it.solve_damped(self.lambda, times) {
            Ok(ControlFlow::Break(())) => ControlFlow::Break(()),
            Ok(ControlFlow::Continue(())) => ControlFlow::Continue(Proposal::Step {
                predicted: dot(&it.delta, &it.b) + it.damping_term(self.lambda),
                undamped: self.lambda == 0.0,
            }),
            Err(_) => {
                // Not positive definite at this damping: damp more.
                self.reject();
                it.delta.fill(0.0);
                ControlFlow::Continue(Proposal::Skip)
            }
        }
    }

    /// Accepts a finite trial that lowered chi2 as the model predicted a decrease (gain ratio
    /// ρ > 0), shrinking λ; otherwise rejects it and grows λ.
    pub(super) fn judge(&mut self, chi2: f64, trial: f64, predicted: f64) -> bool {
        let rho = (chi2 - trial) / predicted;
        if trial.is_finite() && rho > 0.0 && predicted > 0.0 {
            self.lambda = decrease_damping(self.lambda, rho);
            self.nu = 2.0;
            true
        } else {
            self.reject();
            false
        }
    }

    fn reject(&mut self) {
        self.lambda = increase_damping(self.lambda, &mut self.nu, self.initial_lambda);
    }

    pub(super) fn out_of_range(&self) -> Option<Termination> {
        (self.lambda > MAX_LAMBDA).then(|| {
            termination(
                TerminationReason::NoProgress,
                self.lambda,
                MAX_LAMBDA,
                "no acceptable step: damping / trust region out of range",
            )
        })
    }
}

impl Iterations<'_> {
    /// D's entry for scalar column `c`.
    pub(super) fn damping_diagonal(&self, c: usize) -> f64 {
        let (low, high) = DAMPING_DIAGONAL_RANGE;
        self.h[self.layout.pattern.diagonal_index(c)].clamp(low, high)
    }

    /// λ·ΔᵀDΔ.
    pub(super) fn damping_term(&self, lambda: f64) -> f64 {
        (0..self.layout.n())
            .map(|c| lambda * self.damping_diagonal(c) * self.delta[c] * self.delta[c])
            .sum()
    }
}

/// Nielsen's acceptance rule λ ← λ·max(1/3, 1 − (2ρ − 1)³) for gain ratio `rho`, dropping to 0
/// below [`LAMBDA_SNAP_TO_ZERO`].
fn decrease_damping(mut lambda: f64, rho: f64) -> f64 {
    lambda *= (1.0f64 / 3.0).max(1.0 - (2.0 * rho - 1.0).powi(3));
    if lambda < LAMBDA_SNAP_TO_ZERO {
        lambda = 0.0;
    }
    lambda
}

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
