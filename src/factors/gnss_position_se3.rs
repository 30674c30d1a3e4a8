//! A GNSS position fix of one SE(3) pose: the pose's origin measured in the world frame.
//!
//! With the pose `X = (R, t)` and the measured world position `p`, the error is
//!
//! ```text
//! e = t − p                                   (3 × 1, metres, world frame)
//! ```
//!
//! For the retraction `(R, t) ⊕ (v, ω) = (R Exp(ω), t + R v)` the translation moves by `R v` and
//! does not depend on `ω`, so
//!
//! ```text
//! ∂e/∂(v, ω) = [ R   0 ]                      (3 × 6)
//! ```
//!
//! The information matrix is over the world axes (x, y, z), e.g. a receiver's ENU covariance
//! inverted. The antenna is taken to sit at the pose's origin (no lever arm). The factor leaves
//! the orientation unconstrained, so it predicts no initial value: a pose it alone touches has no
//! rotation to start from.

use nalgebra::Vector3;

use super::between_se3::put_block;
use super::{expect_kind, EvaluationError, Factor, FactorWire};
use crate::geometry::Se3;
use crate::variables::{Key, Variable};

#[derive(Clone, Debug)]
pub struct GnssPositionSe3 {
    keys: [Key; 1],
    /// Measured position of the pose's origin, in the world frame.
    pub position: Vector3<f64>,
}

impl GnssPositionSe3 {
    /// The wire form: `gnss_position_se3`.
    pub const WIRE: FactorWire = FactorWire {
        name: "gnss_position_se3",
        variable_kinds: &["se3"],
        key_names: &["i"],
        measurement_len: 3,
        measurement: &["x", "y", "z"],
        residual_dim: 3,
        description: "A GNSS fix: the measured world position of the pose's origin (no lever arm), in the world frame of the poses. Residual t - p in metres over the world axes (x, y, z); the orientation is not constrained.",
        build: |k, m| Ok(Box::new(GnssPositionSe3::new(k[0], Vector3::new(m[0], m[1], m[2])))),
    };

    pub fn new(key: Key, position: Vector3<f64>) -> Self {
        Self {
            keys: [key],
            position,
        }
    }
}

impl Factor for GnssPositionSe3 {
    answered_by_wire!();
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let x: &Se3 = expect_kind(variables, 0, "se3")?;
        let e = x.translation - self.position;
        error.copy_from_slice(e.as_slice());
        if let Some(j) = jacobian {
            j.fill(0.0);
            put_block(j, 6, 0, 0, &x.rotation_matrix());
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::testing::{assert_jacobians_match, Rng};

    #[test]
    fn jacobians_match_numeric() {
        let mut rng = Rng::new(29);
        for _ in 0..100 {
            let factor = GnssPositionSe3::new(0, rng.vector3(10.0));
            assert_jacobians_match(&factor, &[Box::new(rng.se3())]);
        }
    }

    #[test]
    fn error_is_the_translation_minus_the_fix_whatever_the_rotation() {
        let mut rng = Rng::new(31);
        let x = rng.se3();
        let p = Vector3::new(1.0, -2.0, 0.5);
        let factor = GnssPositionSe3::new(0, p);
        let mut e = [0.0; 3];
        factor.evaluate(&[&x], &mut e, None).unwrap();
        let expected = x.translation - p;
        assert_eq!(e, [expected.x, expected.y, expected.z]);
        let turned = Se3::new(rng.se3().rotation, x.translation);
        let mut e2 = [0.0; 3];
        factor.evaluate(&[&turned], &mut e2, None).unwrap();
        assert_eq!(e, e2);
    }
}
