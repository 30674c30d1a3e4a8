//! The range between two planar poses' positions (UWB ranging between robots).
//!
//! `e = ‖t_j − t_i‖ − r` (metres). With `u = (t_j − t_i)/‖t_j − t_i‖` and additive retraction in
//! `(x, y, θ)`: `∂e/∂x_i = [−uᵀ  0]`, `∂e/∂x_j = [uᵀ  0]` (`u = 0` where the positions meet).

use nalgebra::Vector2;

use super::range_se2_point2::distance_and_direction2;
use super::{expect_kind, EvaluationError, Factor};
use crate::geometry::Se2;
use crate::variables::Variable;

range_factor!(RangeSe2, "range_se2", &["se2", "se2"], &["i", "j"], "Range in metres between the positions of two se2 poses (UWB ranging between robots). Residual |t_j - t_i| - r.");

impl Factor for RangeSe2 {
    answered_by_wire!();
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let a: &Se2 = expect_kind(variables, 0, "se2")?;
        let b: &Se2 = expect_kind(variables, 1, "se2")?;
        let (e, u) = distance_and_direction2(Vector2::new(b.x - a.x, b.y - a.y));
        error[0] = e - self.range;
        if let Some(j) = jacobian {
            j.copy_from_slice(&[-u.x, -u.y, 0.0, u.x, u.y, 0.0]);
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
        let mut rng = Rng::new(73);
        for _ in 0..100 {
            let f = RangeSe2::new(0, 1, 3.0 * rng.uniform());
            assert_jacobians_match(&f, &[Box::new(rng.se2()), Box::new(rng.se2())]);
        }
    }
}
