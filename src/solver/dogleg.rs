//! Powell's Dogleg: the Gauss-Newton step it starts from (damped just enough when H is
//! singular), the step inside the trust radius between the Cauchy point and that GN step, and
//! the radius update from the gain ratio.

use std::ops::ControlFlow;

use super::iterations::{dot, Iterations, StepTimes};
use super::linearize::symmetric_multiply;
use super::SolverError;
use crate::problem::Values;

impl Iterations<'_> {
    /// Gauss-Newton step for Dogleg into `work`; a singular H gets the smallest damping that works.
    pub(super) fn dogleg_gauss_newton_step(
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
    pub(super) fn dogleg_step(&mut self, radius: f64) -> f64 {
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

/// The next trust radius after a step of length `step` with gain ratio `rho`: grow it after a
/// step the model predicted well, shrink it after a poor or non-finite one.
pub(super) fn update_trust_radius(radius: f64, rho: f64, step: f64, trial_finite: bool) -> f64 {
    if rho > 0.75 {
        radius.max(3.0 * step)
    } else if rho < 0.25 || !trial_finite {
        0.5 * step.min(radius)
    } else {
        radius
    }
}
