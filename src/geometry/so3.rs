//! 3D rotations: hat, exp/log and the right Jacobians, all safe near θ = 0 and θ = π.
//!
//! Rotations are stored as unit quaternions (Hamilton, as nalgebra and the g2o files use). The
//! logarithm goes through the quaternion with `atan2`, which stays accurate where the usual
//! `acos((tr R − 1)/2)` formula loses half its digits (θ near 0 and near π).

use nalgebra::{Matrix3, Quaternion, UnitQuaternion, Vector3};

/// Below this angle the closed forms are replaced by their Taylor series.
const SMALL_ANGLE: f64 = 1e-5;

/// The skew-symmetric matrix `[v]×` with `[v]× w = v × w`.
/// How far a quaternion's norm may be from 1 before it is refused instead of normalised: one rule
/// for poses in batches, fusion messages and ROS orientations. Normalising a far-off one (norm
/// 1e-160, all zeros) would store a rotation nobody meant, or NaN.
pub const UNIT_NORM_TOLERANCE: f64 = 1e-3;

/// The rotation of `q`, normalised, when its norm is within [`UNIT_NORM_TOLERANCE`] of 1;
/// otherwise `Err` with the norm (a NaN norm included).
pub fn unit_within_tolerance(q: Quaternion<f64>) -> Result<UnitQuaternion<f64>, f64> {
    let norm = q.norm();
    match (norm - 1.0).abs() <= UNIT_NORM_TOLERANCE {
        true => Ok(UnitQuaternion::from_quaternion(q)),
        false => Err(norm),
    }
}

pub fn hat(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// `Exp(ω)`: rotation by |ω| about ω/|ω|.
pub fn exp(omega: &Vector3<f64>) -> UnitQuaternion<f64> {
    let theta_sq = omega.norm_squared();
    let theta = theta_sq.sqrt();
    let half = 0.5 * theta;
    // sin(θ/2)/θ, with its series below the threshold.
    let (w, k) = if theta < SMALL_ANGLE {
        (1.0 - theta_sq / 8.0, 0.5 - theta_sq / 48.0)
    } else {
        (half.cos(), half.sin() / theta)
    };
    UnitQuaternion::new_normalize(Quaternion::new(w, k * omega.x, k * omega.y, k * omega.z))
}

/// `Log(q)` ∈ ℝ³ with |Log(q)| ∈ [0, π]. q and −q give the same answer.
pub fn log(q: &UnitQuaternion<f64>) -> Vector3<f64> {
    let q = q.quaternion();
    let (w, v) = if q.w < 0.0 {
        (-q.w, -q.imag())
    } else {
        (q.w, q.imag())
    };
    let sin_half = v.norm();
    if sin_half < SMALL_ANGLE {
        // θ = 2 atan2(s, w) ≈ 2 s / w (1 − s²/(3w²)); scale = θ / s.
        let scale = 2.0 / w * (1.0 - sin_half * sin_half / (3.0 * w * w));
        return v * scale;
    }
    let theta = 2.0 * sin_half.atan2(w);
    v * (theta / sin_half)
}

/// Right Jacobian J_r(φ): `Exp(φ + δ) ≈ Exp(φ) Exp(J_r(φ) δ)`.
pub fn right_jacobian(phi: &Vector3<f64>) -> Matrix3<f64> {
    let theta_sq = phi.norm_squared();
    let theta = theta_sq.sqrt();
    let k = hat(phi);
    let (a, b) = if theta < SMALL_ANGLE {
        (0.5 - theta_sq / 24.0, 1.0 / 6.0 - theta_sq / 120.0)
    } else {
        (
            (1.0 - theta.cos()) / theta_sq,
            (theta - theta.sin()) / (theta_sq * theta),
        )
    };
    Matrix3::identity() - k * a + k * k * b
}

/// Inverse right Jacobian J_r⁻¹(φ): `Log(Exp(φ) Exp(δ)) ≈ φ + J_r⁻¹(φ) δ`.
///
/// The `[φ]×²` coefficient is `1/θ² − (1 + cos θ)/(2θ sin θ)`, which is 0/0 at θ = π in that form;
/// `(1 + cos θ)/sin θ = cot(θ/2)` removes the singularity, so the value stays finite up to π.
pub fn right_jacobian_inv(phi: &Vector3<f64>) -> Matrix3<f64> {
    let theta_sq = phi.norm_squared();
    let theta = theta_sq.sqrt();
    let k = hat(phi);
    let c = if theta < SMALL_ANGLE {
        1.0 / 12.0 + theta_sq / 720.0
    } else {
        let half = 0.5 * theta;
        1.0 / theta_sq - half.cos() / (half.sin() * 2.0 * theta)
    };
    Matrix3::identity() + k * 0.5 + k * k * c
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    fn vectors() -> Vec<Vector3<f64>> {
        let axis = Vector3::new(0.3, -0.5, 0.8).normalize();
        [0.0, 1e-12, 1e-7, 1e-3, 0.5, 2.0, 3.0, PI - 1e-6, PI - 1e-10]
            .iter()
            .map(|&t| axis * t)
            .collect()
    }

    #[test]
    fn exp_log_round_trip() {
        for phi in vectors() {
            let back = log(&exp(&phi));
            assert!(
                (back - phi).norm() < 1e-9 * (1.0 + phi.norm()),
                "{phi:?} -> {back:?}"
            );
        }
    }

    #[test]
    fn log_at_pi_has_angle_pi() {
        let q = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), PI);
        assert!((log(&q).norm() - PI).abs() < 1e-12);
        let minus = UnitQuaternion::new_unchecked(-q.into_inner());
        assert!((log(&minus).norm() - PI).abs() < 1e-12);
    }

    #[test]
    fn jacobian_inverse_is_inverse() {
        for phi in vectors() {
            let prod = right_jacobian(&phi) * right_jacobian_inv(&phi);
            assert!(
                (prod - Matrix3::identity()).norm() < 1e-8,
                "{phi:?}: {prod}"
            );
        }
    }

    #[test]
    fn right_jacobian_matches_numeric() {
        // Central differences of Log lose accuracy within ~1e-5 of π (its third derivative grows
        // like 1/(π − θ)²); `jacobian_inverse_is_inverse` covers that range exactly.
        let axis = Vector3::new(0.3, -0.5, 0.8).normalize();
        let near_pi = [PI - 1e-4, PI - 1e-3].map(|t| axis * t);
        for phi in vectors()
            .into_iter()
            .filter(|p| p.norm() < 3.0)
            .chain(near_pi)
        {
            let jr_inv = right_jacobian_inv(&phi);
            let h = 1e-7;
            for k in 0..3 {
                let mut d = Vector3::zeros();
                d[k] = h;
                let plus = log(&(exp(&phi) * exp(&d)));
                let minus = log(&(exp(&phi) * exp(&-d)));
                let col = (plus - minus) / (2.0 * h);
                assert!((col - jr_inv.column(k)).norm() < 1e-5, "{phi:?} col {k}");
            }
        }
    }
}
