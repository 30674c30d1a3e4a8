//! The range from a planar pose to a `point2` landmark (a UWB beacon, a radio anchor).
//!
//! With the pose's position `t` and the landmark `l`: `e = ‖l − t‖ − r` (metres). With
//! `u = (l − t)/‖l − t‖` and the pose retracting additively in `(x, y, θ)`:
//! `∂e/∂(x, y, θ) = [−uᵀ  0]`, `∂e/∂l = uᵀ`. At `l = t` the direction is undefined and `u` is
//! taken as 0 (a zero Jacobian rather than a non-finite one).

use nalgebra::Vector2;

use super::{expect_kind, EvaluationError, Factor};
use crate::geometry::{Point2, Se2};
use crate::variables::Variable;

range_factor!(RangeSe2Point2, "range_se2_point2", &["se2", "point2"], &["pose", "landmark"], "Range in metres from an se2 pose's position to a point2 landmark (a UWB or radio beacon). Residual |l - t| - r.");

/// `‖d‖` and `d/‖d‖` (0 for `d = 0`).
pub(crate) fn distance_and_direction2(d: Vector2<f64>) -> (f64, Vector2<f64>) {
    let n = d.norm();
    (n, if n > 0.0 { d / n } else { Vector2::zeros() })
}

impl Factor for RangeSe2Point2 {
    answered_by_wire!();
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let x: &Se2 = expect_kind(variables, 0, "se2")?;
        let l: &Point2 = expect_kind(variables, 1, "point2")?;
        let d = l.0 - Vector2::new(x.x, x.y);
        let (e, u) = distance_and_direction2(d);
        error[0] = e - self.range;
        if let Some(j) = jacobian {
            j.copy_from_slice(&[-u.x, -u.y, 0.0, u.x, u.y]);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::testing::{assert_jacobians_match, Rng};
    use crate::geometry::Point2;
    use nalgebra::Vector2;

    #[test]
    fn jacobians_match_numeric() {
        let mut rng = Rng::new(71);
        for _ in 0..100 {
            let f = RangeSe2Point2::new(0, 1, 3.0 * rng.uniform());
            assert_jacobians_match(
                &f,
                &[
                    Box::new(rng.se2()),
                    Box::new(Point2(Vector2::new(5.0 * rng.normal(), 5.0 * rng.normal()))),
                ],
            );
        }
    }
}
