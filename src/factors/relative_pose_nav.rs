//! Relative pose between two navigation states (lidar odometry): the pose of keyframe j seen
//! from keyframe i, measured as `(Δp, ΔR)` in frame i.
//!
//! ```text
//! e_p = R_iᵀ (p_j − p_i) − Δp
//! e_θ = Log(ΔRᵀ R_iᵀ R_j)
//! ```
//!
//! With the right perturbation `R ← R Exp(δθ)` and additive p (see [`NavState`]), `A = R_iᵀ R_j`:
//!
//! ```text
//! ∂e_p/∂p_i = −R_iᵀ    ∂e_p/∂θ_i = [R_iᵀ (p_j − p_i)]×    ∂e_p/∂p_j = R_iᵀ
//! ∂e_θ/∂θ_i = −J_r⁻¹(e_θ) Aᵀ                               ∂e_θ/∂θ_j = J_r⁻¹(e_θ)
//! ```
//!
//! (`R_iᵀ → Exp(−δ) R_iᵀ` moves E = ΔRᵀ A to E Exp(−Aᵀ δ); `R_j → R_j Exp(δ)` to E Exp(δ).)
//! Velocity and bias columns are zero. The Jacobian is `[J_i (6×15) | J_j (6×15)]`.

use std::any::Any;

use nalgebra::{UnitQuaternion, Vector3};

use super::between_se3::put_block;
use super::{expect_kind, EvaluationError, Factor};
use crate::geometry::nav_state::{P, THETA};
use crate::geometry::{so3, NavState};
use crate::variables::{Key, Variable};

#[derive(Clone, Debug)]
pub struct RelativePoseNav {
    keys: [Key; 2],
    pub delta_position: Vector3<f64>,
    pub delta_rotation: UnitQuaternion<f64>,
}

impl RelativePoseNav {
    pub fn new(
        from: Key,
        to: Key,
        delta_position: Vector3<f64>,
        delta_rotation: UnitQuaternion<f64>,
    ) -> Self {
        Self {
            keys: [from, to],
            delta_position,
            delta_rotation,
        }
    }
}

/// The name RelativePoseNav answers (internal: refused as a user-defined type name).
pub const NAME: &str = "relative_pose_nav";

impl Factor for RelativePoseNav {
    fn name(&self) -> &'static str {
        NAME
    }
    fn keys(&self) -> &[Key] {
        &self.keys
    }
    fn residual_dim(&self) -> usize {
        6
    }
    fn variable_kinds(&self) -> &[&'static str] {
        &["nav_state", "nav_state"]
    }
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let i: &NavState = expect_kind(variables, 0, "nav_state")?;
        let j: &NavState = expect_kind(variables, 1, "nav_state")?;
        let ri_t = i.rotation.inverse();
        let d = ri_t * (j.position - i.position);
        let e_p = d - self.delta_position;
        let relative = ri_t * j.rotation;
        let e_theta = so3::log(&(self.delta_rotation.inverse() * relative));
        error[..3].copy_from_slice(e_p.as_slice());
        error[3..6].copy_from_slice(e_theta.as_slice());
        if let Some(jac) = jacobian {
            jac.fill(0.0);
            let ri_t = ri_t.to_rotation_matrix().into_inner();
            let jr_inv = so3::right_jacobian_inv(&e_theta);
            let a_t = relative.inverse().to_rotation_matrix().into_inner();
            put_block(jac, 30, 0, P, &-ri_t);
            put_block(jac, 30, 0, THETA, &so3::hat(&d));
            put_block(jac, 30, 0, 15 + P, &ri_t);
            put_block(jac, 30, 3, THETA, &-(jr_inv * a_t));
            put_block(jac, 30, 3, 15 + THETA, &jr_inv);
        }
        Ok(())
    }
    fn as_any(&self) -> &dyn Any {
        self
    }
    /// The far state from the near one: pose composed, velocity and biases carried over.
    fn predict(&self, known: &[Option<&dyn Variable>], target: usize) -> Option<Box<dyn Variable>> {
        let other = known[1 - target]?.as_any().downcast_ref::<NavState>()?;
        let mut state = *other;
        if target == 1 {
            state.position = other.position + other.rotation * self.delta_position;
            state.rotation = other.rotation * self.delta_rotation;
        } else {
            state.rotation = other.rotation * self.delta_rotation.inverse();
            state.position = other.position - state.rotation * self.delta_position;
        }
        Some(Box::new(state))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::testing::{assert_jacobians_match, Rng};

    #[test]
    fn jacobians_match_numeric() {
        let mut rng = Rng::new(31);
        for _ in 0..100 {
            let z = rng.se3();
            let f = RelativePoseNav::new(0, 1, z.translation, z.rotation);
            assert_jacobians_match(&f, &[Box::new(rng.nav_state()), Box::new(rng.nav_state())]);
        }
    }
}
