//! Powell's Dogleg: the Gauss-Newton step it starts from (damped just enough when H is
//! singular), the step inside the trust radius between the Cauchy point and that GN step, and
//! the radius update from the gain ratio.

use std::ops::ControlFlow;

use super::iterations::{Iterations, StepTimes};
use super::linearize::symmetric_multiply;
use super::options::SolverOptions;
use super::stopping::termination;
use super::strategy::Proposal;
use super::summary::{Termination, TerminationReason};
use super::vector::dot;
use super::SolverError;
use crate::problem::Values;

/// Below this radius the steps are too short to matter: the solve ends without progress.
const MIN_TRUST_RADIUS: f64 = 1e-16;

/// A singular H gets the damping μ·I for the Gauss-Newton step, μ starting here and growing by
/// [`SINGULAR_DAMPING_GROWTH`] until the factorisation works, up to [`SINGULAR_DAMPING_MAX`].
const SINGULAR_DAMPING_START: f64 = 1e-10;
const SINGULAR_DAMPING_GROWTH: f64 = 100.0;
const SINGULAR_DAMPING_MAX: f64 = 1e8;

pub(super) struct Dogleg {
    pub(super) radius: f64,
    /// `work` holds the Gauss-Newton step of the current point (kept across rejections: only
    /// the radius changes until a step is accepted).
    have_gn_step: bool,
}

impl Dogleg {
    pub(super) fn new(options: &SolverOptions) -> Self {
        Self {
            radius: options.initial_trust_radius,
            have_gn_step: false,
        }
    }

    pub(super) fn compute_step(
        &mut self,
        it: &mut Iterations<'_>,
        values: &Values,
        times: &mut StepTimes,
    ) -> Result<ControlFlow<(), Proposal>, SolverError> {
        if !self.have_gn_step {
            if it.dogleg_gauss_newton_step(values, times)?.is_break() {
                return Ok(ControlFlow::Break(()));
            }
            self.have_gn_step = true;
        }
        let (predicted, undamped) = it.dogleg_step(self.radius);
        Ok(ControlFlow::Continue(Proposal::Step {
            predicted,
            undamped,
        }))
    }

    /// Accepts a finite trial with a positive gain ratio; the radius follows the gain ratio.
    pub(super) fn judge(&mut self, chi2: f64, trial: f64, predicted: f64, step: f64) -> bool {
        let rho = (chi2 - trial) / predicted;
        self.radius = update_trust_radius(self.radius, rho, step, trial.is_finite());
        trial.is_finite() && rho > 0.0 && predicted > 0.0
    }

    pub(super) fn step_done(&mut self, accepted: bool) {
        if accepted {
            self.have_gn_step = false;
        }
    }

    pub(super) fn out_of_range(&self) -> Option<Termination> {
        (self.radius < MIN_TRUST_RADIUS).then(|| {
            termination(
                TerminationReason::NoProgress,
                self.radius,
                MIN_TRUST_RADIUS,
                "no acceptable step: damping / trust region out of range",
            )
        })
    }
}

impl Iterations<'_> {
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
                Err(e) if mu > SINGULAR_DAMPING_MAX => return Err(self.indeterminate(values, e)),
                Err(_) if mu == 0.0 => mu = SINGULAR_DAMPING_START,
                Err(_) => mu *= SINGULAR_DAMPING_GROWTH,
            }
        }
        std::mem::swap(&mut self.work, &mut self.delta);
        Ok(ControlFlow::Continue(()))
    }

    /// Powell's dogleg inside `radius` from the GN step (in `work`) and the Cauchy point; writes
    /// the step to `delta` and returns the model decrease 2Δᵀb − ΔᵀHΔ and whether the step is
    /// the whole Gauss-Newton step.
    fn dogleg_step(&mut self, radius: f64) -> (f64, bool) {
        let pattern = &self.layout.pattern;
        let gn_norm = dot(&self.work, &self.work).sqrt();
        let inside = gn_norm <= radius;
        if inside {
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
        let predicted = 2.0 * dot(&self.delta, &self.b) - dot(&self.delta, &self.product);
        // Inside the radius the step is the Gauss-Newton step (damped only when H is singular).
        (predicted, inside)
    }
}

/// The next trust radius after a step of length `step` with gain ratio `rho`: grow it after a
/// step the model predicted well, shrink it after a poor or non-finite one.
fn update_trust_radius(radius: f64, rho: f64, step: f64, trial_finite: bool) -> f64 {
    if rho > 0.75 {
        radius.max(3.0 * step)
    } else if rho < 0.25 || !trial_finite {
        0.5 * step.min(radius)
    } else {
        radius
    }
}
