//! The range from an SE(3) pose to a `point3` landmark (a UWB beacon).
//!
//! `e = ‖l − t‖ − r` (metres). With `u = (l − t)/‖l − t‖` and the retraction
//! `(R, t) ⊕ (v, ω) = (R Exp(ω), t + R v)`, `t` moves by `R v`: `∂e/∂(v, ω) = [−uᵀR  0]`,
//! `∂e/∂l = uᵀ` (`u = 0` at `l = t`).

use nalgebra::Vector3;

use super::{expect_kind, EvaluationError, Factor};
use crate::geometry::{Point3, Se3};
use crate::variables::Variable;

range_factor!(RangeSe3Point3, "range_se3_point3", &["se3", "point3"], &["pose", "landmark"], "Range in metres from an se3 pose's position to a point3 landmark (a UWB beacon). Residual |l - t| - r.");

/// `‖d‖` and `d/‖d‖` (0 for `d = 0`).
pub(crate) fn distance_and_direction3(d: Vector3<f64>) -> (f64, Vector3<f64>) {
    let n = d.norm();
    (n, if n > 0.0 { d / n } else { Vector3::zeros() })
}

impl Factor for RangeSe3Point3 {
    answered_by_wire!();
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let x: &Se3 = expect_kind(variables, 0, "se3")?;
        let l: &Point3 = expect_kind(variables, 1, "point3")?;
        let (e, u) = distance_and_direction3(l.0 - x.translation);
        error[0] = e - self.range;
        if let Some(j) = jacobian {
            let ur = x.rotation_matrix().transpose() * u; // (uᵀ R)ᵀ
            j.fill(0.0);
            j[..3].copy_from_slice(&[-ur.x, -ur.y, -ur.z]);
            j[6..9].copy_from_slice(&[u.x, u.y, u.z]);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::testing::{assert_jacobians_match, Rng};
    use crate::geometry::Point3;

    #[test]
    fn jacobians_match_numeric() {
        let mut rng = Rng::new(79);
        for _ in 0..100 {
            let f = RangeSe3Point3::new(0, 1, 3.0 * rng.uniform());
            assert_jacobians_match(
                &f,
                &[Box::new(rng.se3()), Box::new(Point3(rng.vector3(5.0)))],
            );
        }
    }
}
