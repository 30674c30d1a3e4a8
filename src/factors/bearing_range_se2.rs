//! A landmark seen from a planar pose: its bearing and range in the pose's frame (a laser or
//! radar return, Victoria Park's trees).
//!
//! With the pose `X = (R(θ), t)`, the landmark `l` and the measurement `(b, r)`, the landmark in
//! the body frame is `d = Rᵀ (l − t) = (dx, dy)`, and the error is
//!
//! ```text
//! e = [ wrap(atan2(dy, dx) − b) ;  ‖d‖ − r ]            (radians, metres)
//! ```
//!
//! The pose retracts additively in `(x, y, θ)` and the point in `(x, y)`. With `ρ = ‖d‖`,
//! `∂d/∂t = −Rᵀ`, `∂d/∂θ = (dy, −dx)`, `∂d/∂l = Rᵀ`, `∂atan2/∂d = (−dy, dx)/ρ²` and
//! `∂ρ/∂d = (dx, dy)/ρ`, so
//!
//! ```text
//! ∂e/∂(x, y, θ) = [ (−dy, dx)/ρ² · (−Rᵀ)   −1 ]        ∂e/∂l = [ (−dy, dx)/ρ² · Rᵀ ]
//!                 [ (dx, dy)/ρ  · (−Rᵀ)     0 ]                [ (dx, dy)/ρ  · Rᵀ  ]
//! ```
//!
//! A landmark at the pose's origin (ρ = 0) has no bearing: the error is not finite there, and
//! such a factor is refused when it is added at those values. The factor predicts the landmark
//! from the pose (`t + R r (cos b, sin b)`, how a landmark starts from its first sighting), not
//! the pose from the landmark (a bearing and range leave its orientation open).

use nalgebra::{Matrix2, Vector2};

use super::{expect_kind, EvaluationError, Factor, FactorWire};
use crate::geometry::{rotation_matrix_2d, wrap_angle, Point2, Se2};
use crate::variables::{Key, Variable};

#[derive(Clone, Debug)]
pub struct BearingRangeSe2 {
    keys: [Key; 2],
    /// Bearing in the pose's frame, radians (counter-clockwise from its x axis).
    pub bearing: f64,
    /// Range, metres.
    pub range: f64,
}

impl BearingRangeSe2 {
    /// The wire form: `bearing_range_se2`.
    pub const WIRE: FactorWire = FactorWire {
        name: "bearing_range_se2",
        variable_kinds: &["se2", "point2"],
        key_names: &["pose", "landmark"],
        measurement_len: 2,
        measurement: &["bearing", "range"],
        residual_dim: 2,
        description: "A point2 landmark seen from an se2 pose: bearing (radians, counter-clockwise from the pose's x axis) and range (metres). Residual (wrapped bearing error, range error).",
        build: |k, m| {
            if m[1] < 0.0 {
                return Err(format!("a range cannot be negative, got {}", m[1]));
            }
            Ok(Box::new(BearingRangeSe2::new(k[0], k[1], m[0], m[1])))
        },
    };

    pub fn new(pose: Key, landmark: Key, bearing: f64, range: f64) -> Self {
        Self {
            keys: [pose, landmark],
            bearing,
            range,
        }
    }

    /// GTSAM's reading of a landmark seen at body-frame `(x, y)`: bearing `atan2(y, x)`, range
    /// `√(x² + y²)`.
    pub fn from_body_position(pose: Key, landmark: Key, x: f64, y: f64) -> Self {
        Self::new(pose, landmark, y.atan2(x), x.hypot(y))
    }
}

impl Factor for BearingRangeSe2 {
    answered_by_wire!();
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let x: &Se2 = expect_kind(variables, 0, "se2")?;
        let l: &Point2 = expect_kind(variables, 1, "point2")?;
        let rt: Matrix2<f64> = rotation_matrix_2d(x.theta).transpose();
        let d = rt * (l.0 - Vector2::new(x.x, x.y));
        let rho2 = d.norm_squared();
        let rho = rho2.sqrt();
        error[0] = wrap_angle(d.y.atan2(d.x) - self.bearing);
        error[1] = rho - self.range;
        if let Some(j) = jacobian {
            // Rows: bearing, range; columns: x, y, θ of the pose, then x, y of the landmark.
            let db = Vector2::new(-d.y, d.x) / rho2;
            let dr = d / rho;
            for (row, g) in [db, dr].iter().enumerate() {
                let wrt_l = rt.transpose() * g; // gᵀ Rᵀ, as a column
                let out = &mut j[row * 5..row * 5 + 5];
                out[0] = -wrt_l.x;
                out[1] = -wrt_l.y;
                out[2] = g.x * d.y - g.y * d.x;
                out[3] = wrt_l.x;
                out[4] = wrt_l.y;
            }
        }
        Ok(())
    }

    fn predict(&self, known: &[Option<&dyn Variable>], target: usize) -> Option<Box<dyn Variable>> {
        if target != 1 {
            return None;
        }
        let x = known[0]?.as_any().downcast_ref::<Se2>()?;
        let seen = self.range * Vector2::new(self.bearing.cos(), self.bearing.sin());
        let l = Vector2::new(x.x, x.y) + rotation_matrix_2d(x.theta) * seen;
        Some(Box::new(Point2(l)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::testing::{assert_jacobians_match, Rng};

    fn point(rng: &mut Rng) -> Point2 {
        Point2(Vector2::new(10.0 * rng.normal(), 10.0 * rng.normal()))
    }

    #[test]
    fn jacobians_match_numeric() {
        let mut rng = Rng::new(41);
        for _ in 0..200 {
            let f = BearingRangeSe2::new(0, 1, rng.angle(), 5.0 * rng.uniform());
            assert_jacobians_match(&f, &[Box::new(rng.se2()), Box::new(point(&mut rng))]);
        }
    }

    #[test]
    fn the_predicted_landmark_has_zero_error() {
        let mut rng = Rng::new(43);
        for _ in 0..50 {
            let x = rng.se2();
            let f = BearingRangeSe2::new(0, 1, rng.angle(), 0.5 + 20.0 * rng.uniform());
            let l = f.predict(&[Some(&x), None], 1).unwrap();
            let mut e = [0.0; 2];
            f.evaluate(&[&x, l.as_ref()], &mut e, None).unwrap();
            assert!(e[0].abs() < 1e-12 && e[1].abs() < 1e-12, "{e:?}");
            assert!(f.predict(&[None, Some(l.as_ref())], 0).is_none());
        }
    }

    #[test]
    fn body_position_reads_as_gtsam_does() {
        let f = BearingRangeSe2::from_body_position(0, 1, 3.0, 4.0);
        assert_eq!(f.range, 5.0);
        assert!((f.bearing - 4f64.atan2(3.0)).abs() < 1e-15);
    }
}
