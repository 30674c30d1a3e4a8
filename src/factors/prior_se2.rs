//! Absolute prior on one SE(2) pose: `e = [R_zᵀ (t − t_z); wrap(θ − θ_z)]`, the between error with
//! the first pose at the origin. Jacobian (additive retraction): `[[R_zᵀ, 0], [0, 0, 1]]`.

use super::{expect_kind, EvaluationError, Factor, FactorWire};
use crate::geometry::{wrap_angle, Se2};
use crate::variables::{Key, Variable};

#[derive(Clone, Debug)]
pub struct PriorSe2 {
    keys: [Key; 1],
    pub measurement: Se2,
}

impl PriorSe2 {
    /// The wire form: `prior_se2`.
    pub const WIRE: FactorWire = FactorWire {
        name: "prior_se2",
        variable_kinds: &["se2"],
        key_names: &["i"],
        measurement_len: 3,
        measurement: &["x", "y", "theta"],
        residual_dim: 3,
        description: "An absolute pose. Residual [R_z^T (t - t_z); wrap(theta - theta_z)].",
        build: |k, m| {
            Ok(Box::new(PriorSe2::new(
                k[0],
                Se2::new(m[0], m[1], wrap_angle(m[2])),
            )))
        },
    };

    pub fn new(key: Key, measurement: Se2) -> Self {
        Self {
            keys: [key],
            measurement,
        }
    }
}

impl Factor for PriorSe2 {
    answered_by_wire!();
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let x: &Se2 = expect_kind(variables, 0, "se2")?;
        let z = &self.measurement;
        let (s, c) = z.theta.sin_cos();
        let (dx, dy) = (x.x - z.x, x.y - z.y);
        error[0] = c * dx + s * dy;
        error[1] = -s * dx + c * dy;
        error[2] = wrap_angle(x.theta - z.theta);
        if let Some(j) = jacobian {
            j.copy_from_slice(&[c, s, 0.0, -s, c, 0.0, 0.0, 0.0, 1.0]);
        }
        Ok(())
    }
    fn predict(
        &self,
        _known: &[Option<&dyn Variable>],
        _target: usize,
    ) -> Option<Box<dyn Variable>> {
        Some(Box::new(self.measurement))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::testing::{assert_jacobians_match, Rng};

    #[test]
    fn jacobians_match_numeric() {
        let mut rng = Rng::new(11);
        for _ in 0..100 {
            assert_jacobians_match(&PriorSe2::new(0, rng.se2()), &[Box::new(rng.se2())]);
        }
    }
}
