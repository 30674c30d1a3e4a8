//! A 3D landmark seen from an SE(3) pose as a position in the pose's frame (a stereo camera or
//! lidar point, a tag detection's translation).
//!
//! With the pose `X = (R, t)`, the landmark `l` and the measured body-frame position `z`:
//!
//! ```text
//! d = Rᵀ (l − t)          e = d − z                        (3 × 1, metres, body frame)
//! ```
//!
//! For the retraction `(R, t) ⊕ (v, ω) = (R Exp(ω), t + R v)`: moving `t` by `R v` moves `d` by
//! `−v`; turning by `Exp(ω)` gives `Exp(−ω) d ≈ d + d × ω`; and `∂d/∂l = Rᵀ`. So
//!
//! ```text
//! ∂e/∂(v, ω) = [ −I   [d]× ]        ∂e/∂l = Rᵀ
//! ```
//!
//! It predicts the landmark from the pose (`t + R z`, its first sighting), not the pose.

use nalgebra::{Matrix3, Vector3};

use super::between_se3::put_block;
use super::{expect_kind, EvaluationError, Factor, FactorWire};
use crate::geometry::so3::hat;
use crate::geometry::{Point3, Se3};
use crate::variables::{Key, Variable};

#[derive(Clone, Debug)]
pub struct PositionSe3Point3 {
    keys: [Key; 2],
    /// The landmark's measured position in the pose's frame.
    pub position: Vector3<f64>,
}

impl PositionSe3Point3 {
    /// The wire form: `position_se3_point3`.
    pub const WIRE: FactorWire = FactorWire {
        name: "position_se3_point3",
        variable_kinds: &["se3", "point3"],
        key_names: &["pose", "landmark"],
        measurement_len: 3,
        measurement: &["x", "y", "z"],
        residual_dim: 3,
        description: "A point3 landmark seen from an se3 pose at a position in the pose's frame (stereo, lidar, a tag's translation). Residual R^T (l - t) - z in metres over the pose's axes.",
        build: |k, m| {
            Ok(Box::new(PositionSe3Point3::new(
                k[0],
                k[1],
                Vector3::new(m[0], m[1], m[2]),
            )))
        },
    };

    pub fn new(pose: Key, landmark: Key, position: Vector3<f64>) -> Self {
        Self {
            keys: [pose, landmark],
            position,
        }
    }
}

impl Factor for PositionSe3Point3 {
    answered_by_wire!();
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let x: &Se3 = expect_kind(variables, 0, "se3")?;
        let l: &Point3 = expect_kind(variables, 1, "point3")?;
        let rt = x.rotation_matrix().transpose();
        let d = rt * (l.0 - x.translation);
        error.copy_from_slice((d - self.position).as_slice());
        if let Some(j) = jacobian {
            put_block(j, 9, 0, 0, &-Matrix3::identity());
            put_block(j, 9, 0, 3, &hat(&d));
            put_block(j, 9, 0, 6, &rt);
        }
        Ok(())
    }

    fn predict(&self, known: &[Option<&dyn Variable>], target: usize) -> Option<Box<dyn Variable>> {
        if target != 1 {
            return None;
        }
        let x = known[0]?.as_any().downcast_ref::<Se3>()?;
        Some(Box::new(Point3(
            x.translation + x.rotation_matrix() * self.position,
        )))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::testing::{assert_jacobians_match, Rng};

    #[test]
    fn jacobians_match_numeric() {
        let mut rng = Rng::new(53);
        for _ in 0..100 {
            let f = PositionSe3Point3::new(0, 1, rng.vector3(5.0));
            let l = Point3(rng.vector3(10.0));
            assert_jacobians_match(&f, &[Box::new(rng.se3()), Box::new(l)]);
        }
    }

    #[test]
    fn the_predicted_landmark_has_zero_error() {
        let mut rng = Rng::new(59);
        let x = rng.se3();
        let f = PositionSe3Point3::new(0, 1, rng.vector3(5.0));
        let l = f.predict(&[Some(&x), None], 1).unwrap();
        let mut e = [0.0; 3];
        f.evaluate(&[&x, l.as_ref()], &mut e, None).unwrap();
        assert!(e.iter().all(|v| v.abs() < 1e-12), "{e:?}");
    }
}
