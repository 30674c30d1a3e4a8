//! Levenberg-Marquardt damping: the scaling D = clamp(diag H) of the damped system H + λD, the
//! model-decrease term λΔᵀDΔ, and Nielsen's gain-ratio rules for shrinking λ after an accepted
//! step and growing it after a rejected one.

use super::iterations::Iterations;

impl Iterations<'_> {
    /// D's entry for scalar column `c`: the diagonal of H, clamped as Ceres does so that a zero
    /// or huge curvature still gives a usable damping.
    pub(super) fn damping_diagonal(&self, c: usize) -> f64 {
        self.h[self.layout.pattern.diagonal_index(c)].clamp(1e-6, 1e32)
    }

    /// λ·ΔᵀDΔ.
    pub(super) fn damping_term(&self, lambda: f64) -> f64 {
        (0..self.layout.n())
            .map(|c| lambda * self.damping_diagonal(c) * self.delta[c] * self.delta[c])
            .sum()
    }
}

/// Below this, LM damping is dropped altogether: on pose graphs H is so ill-conditioned that even
/// λ = 1e-9·diag(H) slows the long-wavelength modes, and a full Gauss-Newton step is what converges.
const LAMBDA_SNAP_TO_ZERO: f64 = 1e-9;

/// Nielsen's acceptance rule λ ← λ·max(1/3, 1 − (2ρ − 1)³) for gain ratio `rho`, dropping to 0
/// below [`LAMBDA_SNAP_TO_ZERO`].
pub(super) fn decrease_damping(mut lambda: f64, rho: f64) -> f64 {
    lambda *= (1.0f64 / 3.0).max(1.0 - (2.0 * rho - 1.0).powi(3));
    if lambda < LAMBDA_SNAP_TO_ZERO {
        lambda = 0.0;
    }
    lambda
}

/// Nielsen's rejection rule λ ← λν, ν ← 2ν, starting from `restart` when λ was 0.
pub(super) fn increase_damping(lambda: f64, nu: &mut f64, restart: f64) -> f64 {
    if lambda == 0.0 {
        *nu = 2.0;
        return restart;
    }
    let next = lambda * *nu;
    *nu *= 2.0;
    next
}
