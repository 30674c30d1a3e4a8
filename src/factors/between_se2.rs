//! Relative-pose factor between two SE(2) poses (g2o `EDGE_SE2`, TORO/course `EDGE2`).
//!
//! With `X_i = (t_i, θ_i)`, `X_j = (t_j, θ_j)` and the measurement `Z = (t_ij, θ_ij)` (the pose of
//! j in the frame of i), the error is the course's
//!
//! ```text
//! e = [ R_ijᵀ (R_iᵀ (t_j − t_i) − t_ij) ]
//!     [ wrap(θ_j − θ_i − θ_ij)           ]
//! ```
//!
//! which equals `t2v(Z⁻¹ X_i⁻¹ X_j)`. For the additive SE(2) retraction the Jacobians are
//!
//! ```text
//! A_i = ∂e/∂x_i = [ −R_ijᵀ R_iᵀ   R_ijᵀ (∂R_iᵀ/∂θ_i)(t_j − t_i) ]    B_i = ∂e/∂x_j = [ R_ijᵀ R_iᵀ  0 ]
//!                 [  0  0          −1                          ]                     [ 0  0       1 ]
//! ```

use super::{expect_kind, EvaluationError, Factor, FactorWire};
use crate::geometry::{wrap_angle, Se2};
use crate::variables::{Key, Variable};

#[derive(Clone, Debug)]
pub struct BetweenSe2 {
    keys: [Key; 2],
    pub measurement: Se2,
    /// sin θ_ij and cos θ_ij, so an evaluation needs one `sin_cos` instead of three.
    measurement_sin_cos: (f64, f64),
}

impl BetweenSe2 {
    /// The wire form: `between_se2`.
    pub const WIRE: FactorWire = FactorWire {
        name: "between_se2",
        variable_kinds: &["se2", "se2"],
        key_names: &["i", "j"],
        measurement_len: 3,
        measurement: &["x", "y", "theta"],
        residual_dim: 3,
        description: "The pose of j in the frame of i (g2o EDGE_SE2). Residual [R_ij^T (R_i^T (t_j - t_i) - t_ij); wrap(theta_j - theta_i - theta_ij)].",
        build: |k, m| Ok(Box::new(BetweenSe2::new(k[0], k[1], Se2::new(m[0], m[1], wrap_angle(m[2]))))),
    };

    pub fn new(from: Key, to: Key, measurement: Se2) -> Self {
        Self {
            keys: [from, to],
            measurement,
            measurement_sin_cos: measurement.theta.sin_cos(),
        }
    }
}

impl Factor for BetweenSe2 {
    answered_by_wire!();
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let xi: &Se2 = expect_kind(variables, 0, "se2")?;
        let xj: &Se2 = expect_kind(variables, 1, "se2")?;
        let z = &self.measurement;
        let (si, ci) = xi.theta.sin_cos();
        let (sz, cz) = self.measurement_sin_cos;
        let dx = xj.x - xi.x;
        let dy = xj.y - xi.y;
        // a = R_iᵀ (t_j − t_i)
        let ax = ci * dx + si * dy;
        let ay = -si * dx + ci * dy;
        let ux = ax - z.x;
        let uy = ay - z.y;
        error[0] = cz * ux + sz * uy;
        error[1] = -sz * ux + cz * uy;
        error[2] = wrap_angle(xj.theta - xi.theta - z.theta);
        if let Some(j) = jacobian {
            // M = R_ijᵀ R_iᵀ = R(θ_i + θ_ij)ᵀ
            let (sm, cm) = (si * cz + ci * sz, ci * cz - si * sz);
            // (∂R_iᵀ/∂θ)(t_j − t_i) = [−s dx + c dy, −c dx − s dy] = [a_y, −a_x]
            let gx = cz * ay - sz * ax;
            let gy = -sz * ay - cz * ax;
            j.copy_from_slice(&[
                -cm, -sm, gx, cm, sm, 0.0, //
                sm, -cm, gy, -sm, cm, 0.0, //
                0.0, 0.0, -1.0, 0.0, 0.0, 1.0,
            ]);
        }
        Ok(())
    }
    fn predict(&self, known: &[Option<&dyn Variable>], target: usize) -> Option<Box<dyn Variable>> {
        let other = known[1 - target]?.as_any().downcast_ref::<Se2>()?;
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
        let mut rng = Rng::new(7);
        for _ in 0..200 {
            let f = BetweenSe2::new(0, 1, rng.se2());
            assert_jacobians_match(&f, &[Box::new(rng.se2()), Box::new(rng.se2())]);
        }
    }

    #[test]
    fn error_matches_group_formula() {
        let mut rng = Rng::new(3);
        for _ in 0..50 {
            let (xi, xj, z) = (rng.se2(), rng.se2(), rng.se2());
            let f = BetweenSe2::new(0, 1, z);
            let mut e = [0.0; 3];
            f.evaluate(&[&xi, &xj], &mut e, None).unwrap();
            let g = z.inverse().compose(&xi.inverse().compose(&xj));
            assert!((e[0] - g.x).abs() < 1e-9 && (e[1] - g.y).abs() < 1e-9);
            assert!(wrap_angle(e[2] - g.theta).abs() < 1e-9);
        }
    }
}
