//! Absolute prior on one SE(3) pose: `e = [R_zᵀ (t − t_z); Log(R_zᵀ R)]`.
//! Jacobian for `(R, t) ⊕ (v, ω) = (R Exp(ω), t + R v)`, with `R_E = R_zᵀ R`, `φ = Log(R_E)`:
//! `[[R_E, 0], [0, J_r⁻¹(φ)]]`.

use super::between_se3::put_block;
use super::{expect_kind, EvaluationError, Factor, FactorWire};
use crate::geometry::{so3, Se3};
use crate::variables::se3::decode_se3;
use crate::variables::{Key, Variable};

#[derive(Clone, Debug)]
pub struct PriorSe3 {
    keys: [Key; 1],
    pub measurement: Se3,
}

impl PriorSe3 {
    /// The wire form: `prior_se3`.
    pub const WIRE: FactorWire = FactorWire {
        name: "prior_se3",
        variable_kinds: &["se3"],
        key_names: &["i"],
        measurement_len: 7,
        measurement: &["x", "y", "z", "qx", "qy", "qz", "qw"],
        residual_dim: 6,
        description: "An absolute pose, as an se3 value. Residual [R_z^T (t - t_z); Log(R_z^T R)]: translation in the measured frame, then the rotation angle-axis.",
        build: |k, m| Ok(Box::new(PriorSe3::new(k[0], decode_se3(m)?))),
    };

    pub fn new(key: Key, measurement: Se3) -> Self {
        Self {
            keys: [key],
            measurement,
        }
    }
}

impl Factor for PriorSe3 {
    answered_by_wire!();
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let x: &Se3 = expect_kind(variables, 0, "se3")?;
        let z = &self.measurement;
        let rz_t = z.rotation_matrix().transpose();
        let t_e = rz_t * (x.translation - z.translation);
        let q_e = z.rotation.inverse() * x.rotation;
        let phi = so3::log(&q_e);
        error[..3].copy_from_slice(t_e.as_slice());
        error[3..].copy_from_slice(phi.as_slice());
        if let Some(j) = jacobian {
            j.fill(0.0);
            put_block(j, 6, 0, 0, &q_e.to_rotation_matrix().into_inner());
            put_block(j, 6, 3, 3, &so3::right_jacobian_inv(&phi));
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
        let mut rng = Rng::new(13);
        for _ in 0..100 {
            assert_jacobians_match(&PriorSe3::new(0, rng.se3()), &[Box::new(rng.se3())]);
        }
    }
}
