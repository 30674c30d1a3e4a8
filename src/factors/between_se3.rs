//! Relative-pose factor between two SE(3) poses (g2o `EDGE_SE3:QUAT`).
//!
//! With `E = Z⁻¹ X_i⁻¹ X_j` (`Z` the measured pose of j in the frame of i), the error is
//!
//! ```text
//! e = [ t_E ; Log(R_E) ]   where  R_E = R_zᵀ R_iᵀ R_j,   t_E = R_zᵀ (R_iᵀ (t_j − t_i) − t_z)
//! ```
//!
//! i.e. translation as in g2o and Ceres, rotation as the SO(3) logarithm (the angle, as GTSAM).
//! g2o's own rotation error is `vec(q_E)` ≈ Log(R_E)/2, so a g2o information matrix Ω is mapped
//! onto this error as `D Ω D` with `D = diag(1, 1, 1, ½, ½, ½)` (see `io::g2o`); at the optimum the
//! two objectives differ only by O(θ³) per edge.
//!
//! With the retraction `(R, t) ⊕ (v, ω) = (R Exp(ω), t + R v)` and `φ = Log(R_E)`,
//! `a = R_iᵀ (t_j − t_i)`:
//!
//! ```text
//! ∂e/∂(v_i, ω_i) = [ −R_zᵀ   R_zᵀ [a]×                  ]   ∂e/∂(v_j, ω_j) = [ R_E  0          ]
//!                  [  0     −J_r⁻¹(φ) R_Eᵀ R_zᵀ         ]                    [ 0    J_r⁻¹(φ)   ]
//! ```

use nalgebra::Matrix3;

use super::{expect_kind, EvaluationError, Factor, FactorWire};
use crate::geometry::{so3, Se3};
use crate::variables::se3::decode_se3;
use crate::variables::{Key, Variable};

#[derive(Clone, Debug)]
pub struct BetweenSe3 {
    keys: [Key; 2],
    pub measurement: Se3,
}

impl BetweenSe3 {
    /// The wire form: `between_se3`.
    pub const WIRE: FactorWire = FactorWire {
        name: "between_se3",
        variable_kinds: &["se3", "se3"],
        key_names: &["i", "j"],
        measurement_len: 7,
        measurement: &["x", "y", "z", "qx", "qy", "qz", "qw"],
        residual_dim: 6,
        description: "The pose of j in the frame of i, as an se3 value (g2o EDGE_SE3:QUAT). Residual [t_E; Log(R_E)] with E = Z^-1 X_i^-1 X_j: translation first, then the rotation angle-axis (GTSAM's convention; a g2o information Omega on [t; vec(q)] maps to D Omega D with D = diag(1, 1, 1, 1/2, 1/2, 1/2)).",
        build: |k, m| Ok(Box::new(BetweenSe3::new(k[0], k[1], decode_se3(m)?))),
    };

    pub fn new(from: Key, to: Key, measurement: Se3) -> Self {
        Self {
            keys: [from, to],
            measurement,
        }
    }
}

/// Writes the 3×3 block `m` at (row0, col0) of a row-major matrix with `cols` columns.
pub(crate) fn put_block(j: &mut [f64], cols: usize, row0: usize, col0: usize, m: &Matrix3<f64>) {
    for r in 0..3 {
        for c in 0..3 {
            j[(row0 + r) * cols + col0 + c] = m[(r, c)];
        }
    }
}

impl Factor for BetweenSe3 {
    answered_by_wire!();
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let xi: &Se3 = expect_kind(variables, 0, "se3")?;
        let xj: &Se3 = expect_kind(variables, 1, "se3")?;
        let z = &self.measurement;
        let ri = xi.rotation_matrix();
        let rz_t = z.rotation_matrix().transpose();
        let a = ri.transpose() * (xj.translation - xi.translation);
        let t_e = rz_t * (a - z.translation);
        let q_e = z.rotation.inverse() * xi.rotation.inverse() * xj.rotation;
        let phi = so3::log(&q_e);
        error[..3].copy_from_slice(t_e.as_slice());
        error[3..].copy_from_slice(phi.as_slice());
        if let Some(j) = jacobian {
            j.fill(0.0);
            let r_e = q_e.to_rotation_matrix().into_inner();
            let jr_inv = so3::right_jacobian_inv(&phi);
            put_block(j, 12, 0, 0, &-rz_t);
            put_block(j, 12, 0, 3, &(rz_t * so3::hat(&a)));
            put_block(j, 12, 3, 3, &(-jr_inv * r_e.transpose() * rz_t));
            put_block(j, 12, 0, 6, &r_e);
            put_block(j, 12, 3, 9, &jr_inv);
        }
        Ok(())
    }
    fn predict(&self, known: &[Option<&dyn Variable>], target: usize) -> Option<Box<dyn Variable>> {
        let other = known[1 - target]?.as_any().downcast_ref::<Se3>()?;
        Some(Box::new(match target {
            1 => other.compose(&self.measurement),
            _ => other.compose(&self.measurement.inverse()),
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::testing::{assert_jacobians_match, Rng};

    #[test]
    fn jacobians_match_numeric() {
        let mut rng = Rng::new(5);
        for _ in 0..200 {
            let f = BetweenSe3::new(0, 1, rng.se3());
            assert_jacobians_match(&f, &[Box::new(rng.se3()), Box::new(rng.se3())]);
        }
    }

    #[test]
    fn jacobians_match_numeric_near_pi_error() {
        // Error rotation of almost exactly π: the regime where Jr⁻¹ formulas break.
        let mut rng = Rng::new(9);
        for _ in 0..50 {
            let xi = rng.se3();
            let z = rng.se3();
            let flip = Se3::new(
                so3::exp(
                    &(nalgebra::Vector3::new(0.2, -0.9, 0.4).normalize()
                        * (std::f64::consts::PI - 1e-3)),
                ),
                nalgebra::Vector3::new(0.1, 0.2, 0.3),
            );
            let xj = xi.compose(&z).compose(&flip);
            assert_jacobians_match(&BetweenSe3::new(0, 1, z), &[Box::new(xi), Box::new(xj)]);
        }
    }
}
