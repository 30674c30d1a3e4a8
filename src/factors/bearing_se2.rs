//! A landmark seen from a planar pose by its bearing only (a camera's column, a direction
//! finder): the angle at which the pose sees it, counter-clockwise from the pose's x axis.
//!
//! With the pose `X = (R(θ), t)`, the landmark `l` and the measured bearing `b`, let
//! `d = l − t = (dx, dy)` in the world frame and `ρ² = ‖d‖²`; the error is
//!
//! ```text
//! e = wrap(atan2(dy, dx) − θ − b)                        (radians)
//! ```
//!
//! (the same angle as `atan2` of the body-frame offset `Rᵀ d`). The pose retracts additively in
//! `(x, y, θ)` and the point in `(x, y)`, and `∂atan2(dy, dx)/∂d = (−dy, dx)/ρ²`, so
//!
//! ```text
//! ∂e/∂(x, y, θ) = [ dy/ρ²   −dx/ρ²   −1 ]        ∂e/∂l = [ −dy/ρ²   dx/ρ² ]
//! ```
//!
//! A landmark at the pose's position (ρ = 0) has no bearing: the error is not finite there, and
//! such a factor is refused when it is added at those values. One bearing leaves the landmark's
//! distance open, so the factor predicts nothing: a landmark seen only by bearings needs a value
//! when it is sent (or a sighting with a range).

use nalgebra::Vector2;

use super::{expect_kind, EvaluationError, Factor, FactorWire};
use crate::geometry::{wrap_angle, Point2, Se2};
use crate::variables::{Key, Variable};

#[derive(Clone, Debug)]
pub struct BearingSe2 {
    keys: [Key; 2],
    /// Bearing in the pose's frame, radians (counter-clockwise from its x axis).
    pub bearing: f64,
}

impl BearingSe2 {
    /// The wire form: `bearing_se2`.
    pub const WIRE: FactorWire = FactorWire {
        name: "bearing_se2",
        variable_kinds: &["se2", "point2"],
        key_names: &["pose", "landmark"],
        measurement_len: 1,
        measurement: &["bearing"],
        residual_dim: 1,
        description: "A point2 landmark seen from an se2 pose by its bearing only (radians, counter-clockwise from the pose's x axis). Residual: the wrapped bearing error. The landmark needs a value: one bearing does not place it.",
        build: |k, m| Ok(Box::new(BearingSe2::new(k[0], k[1], m[0]))),
    };

    pub fn new(pose: Key, landmark: Key, bearing: f64) -> Self {
        Self {
            keys: [pose, landmark],
            bearing,
        }
    }
}

impl Factor for BearingSe2 {
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
        let rho2 = d.norm_squared();
        error[0] = wrap_angle(d.y.atan2(d.x) - x.theta - self.bearing);
        if let Some(j) = jacobian {
            let g = Vector2::new(-d.y, d.x) / rho2;
            j.copy_from_slice(&[-g.x, -g.y, -1.0, g.x, g.y]);
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
        let mut rng = Rng::new(47);
        for _ in 0..200 {
            let f = BearingSe2::new(0, 1, rng.angle());
            let l = Point2(Vector2::new(10.0 * rng.normal(), 10.0 * rng.normal()));
            assert_jacobians_match(&f, &[Box::new(rng.se2()), Box::new(l)]);
        }
    }

    #[test]
    fn the_bearing_is_the_body_frame_angle() {
        // A pose at (1, 1) facing +y sees (1, 3) straight ahead and (0, 1) on its left.
        let pose = Se2::new(1.0, 1.0, std::f64::consts::FRAC_PI_2);
        let mut e = [0.0];
        for (l, b) in [((1.0, 3.0), 0.0), ((0.0, 1.0), std::f64::consts::FRAC_PI_2)] {
            let f = BearingSe2::new(0, 1, b);
            let l = Point2(Vector2::new(l.0, l.1));
            f.evaluate(&[&pose, &l], &mut e, None).expect("kinds match");
            assert!(e[0].abs() < 1e-12, "{e:?}");
        }
    }
}
