//! Absolute priors on a navigation state: a full pose (map matching) or a position only (GNSS).
//!
//! ```text
//! pose:      e = [p − p_z; Log(R_zᵀ R)]     ∂e/∂p = I,  ∂e/∂θ = J_r⁻¹(e_θ)   (6 × 15)
//! position:  e = p − p_z                    ∂e/∂p = I                        (3 × 15)
//! ```
//!
//! The position error is in the world frame (a map or GNSS fix is a world-frame measurement);
//! with the right rotation perturbation of [`NavState`] the rotation block is J_r⁻¹.

use std::any::Any;

use nalgebra::{Matrix3, UnitQuaternion, Vector3};

use super::between_se3::put_block;
use super::{expect_kind, EvaluationError, Factor};
use crate::geometry::nav_state::{P, THETA};
use crate::geometry::{so3, NavState};
use crate::variables::{Key, Variable};

#[derive(Clone, Debug)]
pub struct PosePriorNav {
    keys: [Key; 1],
    pub position: Vector3<f64>,
    pub rotation: UnitQuaternion<f64>,
}

impl PosePriorNav {
    pub fn new(key: Key, position: Vector3<f64>, rotation: UnitQuaternion<f64>) -> Self {
        Self {
            keys: [key],
            position,
            rotation,
        }
    }
}

/// The name PosePriorNav answers (internal: refused as a user-defined type name).
pub const POSE_NAME: &str = "pose_prior_nav";
/// The name PositionPriorNav answers (internal: refused as a user-defined type name).
pub const POSITION_NAME: &str = "position_prior_nav";

impl Factor for PosePriorNav {
    fn name(&self) -> &'static str {
        POSE_NAME
    }
    fn keys(&self) -> &[Key] {
        &self.keys
    }
    fn residual_dim(&self) -> usize {
        6
    }
    fn variable_kinds(&self) -> &[&'static str] {
        &["nav_state"]
    }
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let x: &NavState = expect_kind(variables, 0, "nav_state")?;
        let e_p = x.position - self.position;
        let e_theta = so3::log(&(self.rotation.inverse() * x.rotation));
        error[..3].copy_from_slice(e_p.as_slice());
        error[3..6].copy_from_slice(e_theta.as_slice());
        if let Some(j) = jacobian {
            j.fill(0.0);
            put_block(j, 15, 0, P, &Matrix3::identity());
            put_block(j, 15, 3, THETA, &so3::right_jacobian_inv(&e_theta));
        }
        Ok(())
    }
    fn as_any(&self) -> &dyn Any {
        self
    }
}

#[derive(Clone, Debug)]
pub struct PositionPriorNav {
    keys: [Key; 1],
    pub position: Vector3<f64>,
}

impl PositionPriorNav {
    pub fn new(key: Key, position: Vector3<f64>) -> Self {
        Self {
            keys: [key],
            position,
        }
    }
}

impl Factor for PositionPriorNav {
    fn name(&self) -> &'static str {
        POSITION_NAME
    }
    fn keys(&self) -> &[Key] {
        &self.keys
    }
    fn residual_dim(&self) -> usize {
        3
    }
    fn variable_kinds(&self) -> &[&'static str] {
        &["nav_state"]
    }
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let x: &NavState = expect_kind(variables, 0, "nav_state")?;
        error[..3].copy_from_slice((x.position - self.position).as_slice());
        if let Some(j) = jacobian {
            j.fill(0.0);
            put_block(j, 15, 0, P, &Matrix3::identity());
        }
        Ok(())
    }
    fn as_any(&self) -> &dyn Any {
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::testing::{assert_jacobians_match, Rng};

    #[test]
    fn jacobians_match_numeric() {
        let mut rng = Rng::new(37);
        for _ in 0..100 {
            let z = rng.se3();
            let pose = PosePriorNav::new(0, z.translation, z.rotation);
            assert_jacobians_match(&pose, &[Box::new(rng.nav_state())]);
            let position = PositionPriorNav::new(0, z.translation);
            assert_jacobians_match(&position, &[Box::new(rng.nav_state())]);
        }
    }
}
