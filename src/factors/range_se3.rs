//! The range between two SE(3) poses' positions (UWB ranging between robots or drones).
//!
//! `e = ‖t_j − t_i‖ − r` (metres). With `u = (t_j − t_i)/‖t_j − t_i‖` and `t` moving by `R v`:
//! `∂e/∂(v_i, ω_i) = [−uᵀR_i  0]`, `∂e/∂(v_j, ω_j) = [uᵀR_j  0]` (`u = 0` where they meet).

use super::range_se3_point3::distance_and_direction3;
use super::{expect_kind, EvaluationError, Factor};
use crate::geometry::Se3;
use crate::variables::Variable;

range_factor!(RangeSe3, "range_se3", &["se3", "se3"], &["i", "j"], "Range in metres between the positions of two se3 poses (UWB ranging between robots). Residual |t_j - t_i| - r.");

impl Factor for RangeSe3 {
    answered_by_wire!();
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let a: &Se3 = expect_kind(variables, 0, "se3")?;
        let b: &Se3 = expect_kind(variables, 1, "se3")?;
        let (e, u) = distance_and_direction3(b.translation - a.translation);
        error[0] = e - self.range;
        if let Some(j) = jacobian {
            let ua = a.rotation_matrix().transpose() * u;
            let ub = b.rotation_matrix().transpose() * u;
            j.fill(0.0);
            j[..3].copy_from_slice(&[-ua.x, -ua.y, -ua.z]);
            j[6..9].copy_from_slice(&[ub.x, ub.y, ub.z]);
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
        let mut rng = Rng::new(83);
        for _ in 0..100 {
            let f = RangeSe3::new(0, 1, 3.0 * rng.uniform());
            assert_jacobians_match(&f, &[Box::new(rng.se3()), Box::new(rng.se3())]);
        }
    }
}
