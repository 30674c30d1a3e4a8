//! Reprojection error of a 3D point in a BAL (Snavely) camera: predicted minus observed pixel.
//!
//! With `P = R X + t`, `p = −(P.x, P.y)/P.z`, `n = ‖p‖²`, `r = 1 + k1 n + k2 n²`:
//!
//! ```text
//! e = f r p − z
//! ∂e/∂p  = f (r I + 2 (k1 + 2 k2 n) p pᵀ)
//! ∂p/∂P  = [[−1/P.z, 0, P.x/P.z²], [0, −1/P.z, P.y/P.z²]]
//! ∂P/∂ω  = −[R X]×   (rotation perturbed on the left, R ← Exp(ω) R)
//! ∂P/∂t  = I,   ∂P/∂X = R
//! ∂e/∂f  = r p,   ∂e/∂k1 = f n p,   ∂e/∂k2 = f n² p
//! ```
//!
//! The camera's tangent order is (ω, t, f, k1, k2), the point's (x, y, z); the Jacobian is laid
//! out `[J_camera (2×9) | J_point (2×3)]`. Residuals are in pixels (BAL's convention: the cost is
//! ½Σ‖e‖², chi2 is Σ‖e‖² with unit information).

use nalgebra::{Matrix2, Matrix2x3, Vector2};

use super::{expect_kind, EvaluationError, Factor, FactorWire};
use crate::geometry::{so3, Point3, SnavelyCamera};
use crate::variables::{Key, Variable};

#[derive(Clone, Debug)]
pub struct ReprojectionSnavely {
    keys: [Key; 2],
    /// Observed pixel (origin at the image centre, y up).
    pub observed: Vector2<f64>,
}

impl ReprojectionSnavely {
    /// The wire form: `reprojection_snavely`.
    pub const WIRE: FactorWire = FactorWire {
        name: "reprojection_snavely",
        variable_kinds: &["snavely_camera", "point3"],
        key_names: &["camera", "point"],
        measurement_len: 2,
        measurement: &["x", "y"],
        residual_dim: 2,
        description: "The observed pixel with origin at the image centre and y up (BAL). Residual: predicted minus observed pixel, BAL's model p = -P/P.z with radial distortion.",
        build: |k, m| Ok(Box::new(ReprojectionSnavely::new(k[0], k[1], Vector2::new(m[0], m[1])))),
    };

    pub fn new(camera: Key, point: Key, observed: Vector2<f64>) -> Self {
        Self {
            keys: [camera, point],
            observed,
        }
    }
}

impl Factor for ReprojectionSnavely {
    answered_by_wire!();
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let camera: &SnavelyCamera = expect_kind(variables, 0, "snavely_camera")?;
        let point: &Point3 = expect_kind(variables, 1, "point3")?;
        let rx = camera.rotation * point.0;
        let c = rx + camera.translation;
        let p = Vector2::new(-c.x / c.z, -c.y / c.z);
        let n = p.norm_squared();
        let r = 1.0 + camera.k1 * n + camera.k2 * n * n;
        let f = camera.focal;
        let e = p * (f * r) - self.observed;
        error[0] = e.x;
        error[1] = e.y;
        if let Some(j) = jacobian {
            let de_dp = (Matrix2::identity() * r
                + p * p.transpose() * (2.0 * (camera.k1 + 2.0 * camera.k2 * n)))
                * f;
            let iz = 1.0 / c.z;
            let dp_dc = Matrix2x3::new(-iz, 0.0, c.x * iz * iz, 0.0, -iz, c.y * iz * iz);
            let de_dc = de_dp * dp_dc;
            let de_dw = -(de_dc * so3::hat(&rx));
            let de_dx = de_dc * camera.rotation.to_rotation_matrix().matrix();
            let intrinsics = [p * r, p * (f * n), p * (f * n * n)];
            for row in 0..2 {
                let out = &mut j[row * 12..(row + 1) * 12];
                for k in 0..3 {
                    out[k] = de_dw[(row, k)];
                    out[3 + k] = de_dc[(row, k)];
                    out[9 + k] = de_dx[(row, k)];
                }
                for (k, d) in intrinsics.iter().enumerate() {
                    out[6 + k] = d[row];
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector3;

    use super::*;
    use crate::factors::testing::{assert_jacobians_match, Rng};

    /// A camera and a point in front of it (P.z < 0), with BAL-like intrinsics.
    fn camera_and_point(rng: &mut Rng) -> (SnavelyCamera, Point3) {
        let pose = rng.se3();
        let camera = SnavelyCamera {
            rotation: pose.rotation,
            translation: pose.translation,
            focal: 400.0 + 200.0 * rng.uniform(),
            k1: 0.2 * rng.normal(),
            k2: 0.05 * rng.normal(),
        };
        let in_camera = Vector3::new(rng.normal(), rng.normal(), -2.0 - 8.0 * rng.uniform());
        let world = camera.rotation.inverse() * (in_camera - camera.translation);
        (camera, Point3(world))
    }

    #[test]
    fn jacobians_match_numeric() {
        let mut rng = Rng::new(11);
        for _ in 0..200 {
            let (camera, point) = camera_and_point(&mut rng);
            let f =
                ReprojectionSnavely::new(0, 1, Vector2::new(rng.normal(), rng.normal()) * 100.0);
            assert_jacobians_match(&f, &[Box::new(camera), Box::new(point)]);
        }
    }

    #[test]
    fn error_is_the_bal_projection_minus_the_observation() {
        let mut rng = Rng::new(5);
        let (camera, point) = camera_and_point(&mut rng);
        let z = Vector2::new(3.0, -4.0);
        let mut e = [0.0; 2];
        ReprojectionSnavely::new(0, 1, z)
            .evaluate(&[&camera, &point], &mut e, None)
            .unwrap();
        let expected = camera.project(&point.0) - z;
        assert!((e[0] - expected.x).abs() < 1e-9 && (e[1] - expected.y).abs() < 1e-9);
        let round_trip = SnavelyCamera::from_bal(&camera.to_bal());
        assert!((round_trip.project(&point.0) - camera.project(&point.0)).norm() < 1e-9);
    }
}
