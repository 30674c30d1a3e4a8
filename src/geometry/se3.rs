//! 3D rigid motions as (rotation, translation), and the SE(3) exp/log.

use nalgebra::{Matrix3, UnitQuaternion, Vector3, Vector6};

use super::so3;

/// A 3D pose `x ↦ R x + t`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Se3 {
    pub rotation: UnitQuaternion<f64>,
    pub translation: Vector3<f64>,
}

impl Se3 {
    pub fn new(rotation: UnitQuaternion<f64>, translation: Vector3<f64>) -> Self {
        Self {
            rotation,
            translation,
        }
    }

    pub fn identity() -> Self {
        Self::new(UnitQuaternion::identity(), Vector3::zeros())
    }

    pub fn compose(&self, other: &Se3) -> Se3 {
        Se3::new(
            self.rotation * other.rotation,
            self.translation + self.rotation * other.translation,
        )
    }

    pub fn inverse(&self) -> Se3 {
        let inv = self.rotation.inverse();
        Se3::new(inv, -(inv * self.translation))
    }

    /// `self⁻¹ ∘ other`.
    pub fn between(&self, other: &Se3) -> Se3 {
        self.inverse().compose(other)
    }

    pub fn rotation_matrix(&self) -> Matrix3<f64> {
        self.rotation.to_rotation_matrix().into_inner()
    }

    /// SE(3) exponential of the tangent `(ρ, ω)` (translation part first, as in the g2o files).
    pub fn exp(tangent: &Vector6<f64>) -> Se3 {
        let rho = tangent.fixed_rows::<3>(0).into_owned();
        let omega = tangent.fixed_rows::<3>(3).into_owned();
        // V = J_l(ω) = J_r(−ω).
        let v = so3::right_jacobian(&-omega);
        Se3::new(so3::exp(&omega), v * rho)
    }

    /// Inverse of [`Se3::exp`].
    pub fn log(&self) -> Vector6<f64> {
        let omega = so3::log(&self.rotation);
        let v_inv = so3::right_jacobian_inv(&-omega);
        let rho = v_inv * self.translation;
        Vector6::new(rho.x, rho.y, rho.z, omega.x, omega.y, omega.z)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    #[test]
    fn exp_log_round_trip_including_pi() {
        for &angle in &[0.0, 1e-9, 0.4, 2.5, PI - 1e-8] {
            let axis = Vector3::new(1.0, 2.0, -0.5).normalize() * angle;
            let t = Vector6::new(0.5, -1.0, 2.0, axis.x, axis.y, axis.z);
            let back = Se3::exp(&t).log();
            assert!((back - t).norm() < 1e-7, "{angle}: {back:?}");
        }
    }

    #[test]
    fn between_then_compose_recovers() {
        let a = Se3::exp(&Vector6::new(1.0, 2.0, 3.0, 0.1, -0.2, 0.3));
        let b = Se3::exp(&Vector6::new(-1.0, 0.5, 0.0, 2.0, 0.4, -1.0));
        let back = a.compose(&a.between(&b));
        assert!((back.translation - b.translation).norm() < 1e-12);
        assert!(back.rotation.angle_to(&b.rotation) < 1e-12);
    }
}
