//! A GNSS position fix of an antenna mounted at a lever arm from an SE(3) pose's origin.
//!
//! With the pose `X = (R, t)`, the lever arm `a` (the antenna in the pose's frame) and the
//! measured world position `p`:
//!
//! ```text
//! e = t + R a − p                              (3 × 1, metres, world frame)
//! ```
//!
//! For the retraction `(R, t) ⊕ (v, ω) = (R Exp(ω), t + R v)`: `t` moves by `R v`, and
//! `R Exp(ω) a ≈ R (a + ω × a) = R a − R [a]× ω`, so
//!
//! ```text
//! ∂e/∂(v, ω) = [ R   −R [a]× ]                  (3 × 6)
//! ```
//!
//! With `a = 0` this is `gnss_position_se3`. Unlike it, a lever arm makes the fix depend on the
//! orientation, so several fixes along a trajectory also observe the heading.

use nalgebra::Vector3;

use super::between_se3::put_block;
use super::{expect_kind, EvaluationError, Factor, FactorWire};
use crate::geometry::so3::hat;
use crate::geometry::Se3;
use crate::variables::{Key, Variable};

#[derive(Clone, Debug)]
pub struct GnssLeverArmSe3 {
    keys: [Key; 1],
    /// Measured world position of the antenna.
    pub position: Vector3<f64>,
    /// The antenna in the pose's frame.
    pub lever_arm: Vector3<f64>,
}

impl GnssLeverArmSe3 {
    /// The wire form: `gnss_lever_arm_se3`.
    pub const WIRE: FactorWire = FactorWire {
        name: "gnss_lever_arm_se3",
        variable_kinds: &["se3"],
        key_names: &["i"],
        measurement_len: 6,
        measurement: &["x", "y", "z", "lever_x", "lever_y", "lever_z"],
        residual_dim: 3,
        description: "A GNSS fix of an antenna at a lever arm from the pose's origin: the measured world position (x, y, z) then the antenna's position in the pose's frame (lever_x, lever_y, lever_z). Residual t + R a - p in metres over the world axes.",
        build: |k, m| {
            Ok(Box::new(GnssLeverArmSe3::new(
                k[0],
                Vector3::new(m[0], m[1], m[2]),
                Vector3::new(m[3], m[4], m[5]),
            )))
        },
    };

    pub fn new(key: Key, position: Vector3<f64>, lever_arm: Vector3<f64>) -> Self {
        Self {
            keys: [key],
            position,
            lever_arm,
        }
    }
}

impl Factor for GnssLeverArmSe3 {
    answered_by_wire!();
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let x: &Se3 = expect_kind(variables, 0, "se3")?;
        let r = x.rotation_matrix();
        let e = x.translation + r * self.lever_arm - self.position;
        error.copy_from_slice(e.as_slice());
        if let Some(j) = jacobian {
            put_block(j, 6, 0, 0, &r);
            put_block(j, 6, 0, 3, &-(r * hat(&self.lever_arm)));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::testing::{assert_jacobians_match, Rng};
    use crate::factors::GnssPositionSe3;

    #[test]
    fn jacobians_match_numeric() {
        let mut rng = Rng::new(61);
        for _ in 0..100 {
            let f = GnssLeverArmSe3::new(0, rng.vector3(10.0), rng.vector3(1.0));
            assert_jacobians_match(&f, &[Box::new(rng.se3())]);
        }
    }

    #[test]
    fn without_a_lever_arm_it_is_the_plain_fix() {
        let mut rng = Rng::new(67);
        let x = rng.se3();
        let p = rng.vector3(10.0);
        let (mut a, mut b) = ([0.0; 3], [0.0; 3]);
        GnssLeverArmSe3::new(0, p, Vector3::zeros())
            .evaluate(&[&x], &mut a, None)
            .unwrap();
        GnssPositionSe3::new(0, p)
            .evaluate(&[&x], &mut b, None)
            .unwrap();
        assert_eq!(a, b);
    }
}
