//! Photometric error of a 3D point's 4×4 intensity patch in an image (direct bundle adjustment).
//!
//! The camera pose is `T_cw` (world to camera) as an `se3` variable, perturbed on the right
//! (`R ← R Exp(ω)`, `t ← t + R v`, tangent order (v, ω)); the point is a `point3` in the world.
//! With `P = R X + t`, `(u, v) = π(P)` the pinhole projection and `I` the bilinearly interpolated
//! image, the 16 residuals are, for `k = 4 (du + 2) + (dv + 2)` with `du, dv ∈ {−2, −1, 0, 1}`
//! (the course's order: v fastest):
//!
//! ```text
//! e_k = I(u + du, v + dv) − patch_k
//! ∂e_k/∂P = ∇I(u + du, v + dv)ᵀ ∂π/∂P,    ∂π/∂P = [[fx/Z, 0, −fx X/Z²], [0, fy/Z, −fy Y/Z²]]
//! ∂P/∂v = R,   ∂P/∂ω = −R [X]×,   ∂P/∂X = R
//! ```
//!
//! ∇I is the exact gradient of the bilinear interpolant (see [`GrayImage::sample`]). A point
//! behind the camera, or whose patch (with its interpolation neighbours: u − 2 ≥ 0, u + 2 < W,
//! likewise v) leaves the image, contributes nothing to that image: error and Jacobian are zero,
//! as in the course's reference solutions. The Jacobian is `[J_pose (16×6) | J_point (16×3)]`.

use std::any::Any;
use std::sync::Arc;

use nalgebra::{RowVector3, Vector3};

use super::{expect_kind, EvaluationError, Factor};
use crate::geometry::image::{GrayImage, Pinhole};
use crate::geometry::{so3, Point3, Se3};
use crate::variables::{Key, Variable};

/// Pixels per patch side, and the patch's offsets from the projection.
pub const PATCH_SIDE: usize = 4;
pub const PATCH_PIXELS: usize = PATCH_SIDE * PATCH_SIDE;
const FIRST_OFFSET: f64 = -2.0;

#[derive(Clone, Debug)]
pub struct PhotometricPatch {
    keys: [Key; 2],
    image: Arc<GrayImage>,
    camera: Pinhole,
    /// The point's reference intensities, in the order above.
    pub patch: [f64; PATCH_PIXELS],
}

impl PhotometricPatch {
    pub fn new(
        pose: Key,
        point: Key,
        image: Arc<GrayImage>,
        camera: Pinhole,
        patch: [f64; PATCH_PIXELS],
    ) -> Self {
        Self {
            keys: [pose, point],
            image,
            camera,
            patch,
        }
    }

    /// The projection of world point `x` by `pose` when its whole patch is inside the image.
    pub fn visible_at(&self, pose: &Se3, x: &Vector3<f64>) -> Option<(Vector3<f64>, f64, f64)> {
        let p = pose.rotation * x + pose.translation;
        if p.z.is_nan() || p.z <= 0.0 {
            return None;
        }
        let uv = self.camera.project(&p);
        let (w, h) = (self.image.width as f64, self.image.height as f64);
        let inside = uv.x + FIRST_OFFSET >= 0.0
            && uv.y + FIRST_OFFSET >= 0.0
            && uv.x - FIRST_OFFSET < w
            && uv.y - FIRST_OFFSET < h;
        inside.then_some((p, uv.x, uv.y))
    }

    /// Offsets (du, dv) of patch entry `k`.
    fn offset(k: usize) -> (f64, f64) {
        (
            FIRST_OFFSET + (k / PATCH_SIDE) as f64,
            FIRST_OFFSET + (k % PATCH_SIDE) as f64,
        )
    }
}

/// The name PhotometricPatch answers (internal: refused as a user-defined type name).
pub const NAME: &str = "photometric_patch";

impl Factor for PhotometricPatch {
    fn name(&self) -> &'static str {
        NAME
    }
    fn keys(&self) -> &[Key] {
        &self.keys
    }
    fn residual_dim(&self) -> usize {
        PATCH_PIXELS
    }
    fn variable_kinds(&self) -> &[&'static str] {
        &["se3", "point3"]
    }
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let pose: &Se3 = expect_kind(variables, 0, "se3")?;
        let point: &Point3 = expect_kind(variables, 1, "point3")?;
        let Some((p, u, v)) = self.visible_at(pose, &point.0) else {
            error.fill(0.0);
            if let Some(j) = jacobian {
                j.fill(0.0);
            }
            return Ok(());
        };
        let rotation = pose.rotation.to_rotation_matrix().into_inner();
        let projection = self.camera.project_jacobian(&p);
        let mut jacobian = jacobian;
        for (k, e) in error.iter_mut().enumerate() {
            let (du, dv) = Self::offset(k);
            let s = self
                .image
                .sample(u + du, v + dv)
                .expect("a visible patch lies inside the image");
            *e = s.value - self.patch[k];
            if let Some(j) = jacobian.as_deref_mut() {
                // ∂e/∂P, then through P = R X + t.
                let de_dp: RowVector3<f64> =
                    RowVector3::new(s.dx, s.dy, 0.0).columns(0, 2) * projection;
                let de_dx = de_dp * rotation;
                let de_dw = -(de_dx * so3::hat(&point.0));
                let row = &mut j[k * 9..(k + 1) * 9];
                for c in 0..3 {
                    row[c] = de_dx[c];
                    row[3 + c] = de_dw[c];
                    row[6 + c] = de_dx[c];
                }
            }
        }
        Ok(())
    }
    fn as_any(&self) -> &dyn Any {
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::testing::{assert_jacobians_match, Rng};

    /// A smooth synthetic 640×480 image (so the bilinear interpolant has useful gradients).
    fn image() -> Arc<GrayImage> {
        let (w, h) = (640, 480);
        let pixels = (0..h)
            .flat_map(|y| {
                (0..w).map(move |x| {
                    let (x, y) = (x as f64, y as f64);
                    (120.0 + 60.0 * (x / 9.0).sin() * (y / 7.0).cos() + 0.1 * x) as f32
                })
            })
            .collect();
        Arc::new(GrayImage::new(w, h, pixels).unwrap())
    }

    const CAMERA: Pinhole = Pinhole {
        fx: 277.34,
        fy: 291.402,
        cx: 312.234,
        cy: 239.777,
    };

    #[test]
    fn jacobians_match_numeric() {
        let mut rng = Rng::new(21);
        let image = image();
        let mut checked = 0;
        while checked < 100 {
            let pose = rng.se3();
            let in_camera = Vector3::new(rng.normal(), rng.normal(), 2.0 + 3.0 * rng.uniform());
            let world = pose.rotation.inverse() * (in_camera - pose.translation);
            let mut patch = [0.0; PATCH_PIXELS];
            for v in &mut patch {
                *v = 100.0 + 50.0 * rng.normal();
            }
            let f = PhotometricPatch::new(0, 1, image.clone(), CAMERA, patch);
            if f.visible_at(&pose, &world).is_none() {
                continue;
            }
            assert_jacobians_match(&f, &[Box::new(pose), Box::new(Point3(world))]);
            checked += 1;
        }
    }

    #[test]
    fn residual_follows_the_course_patch_order_and_skips_invisible_points() {
        let image = image();
        let pose = Se3::identity();
        // A point projecting exactly onto pixel (100, 50).
        let z = 4.0;
        let world = Vector3::new(
            (100.0 - CAMERA.cx) * z / CAMERA.fx,
            (50.0 - CAMERA.cy) * z / CAMERA.fy,
            z,
        );
        let f = PhotometricPatch::new(0, 1, image.clone(), CAMERA, [0.0; PATCH_PIXELS]);
        let mut e = [0.0; PATCH_PIXELS];
        f.evaluate(&[&pose, &Point3(world)], &mut e, None).unwrap();
        // k = 4 (du + 2) + (dv + 2): entry 1 is (du, dv) = (−2, −1), entry 4 is (−1, −2).
        for (k, (du, dv)) in [(0, (-2, -2)), (1, (-2, -1)), (4, (-1, -2)), (15, (1, 1))] {
            let expected = image.pixel((100 + du) as usize, (50 + dv) as usize);
            assert!(
                (e[k] - expected).abs() < 1e-6,
                "entry {k}: {} vs {expected}",
                e[k]
            );
        }
        // Behind the camera, and too close to the border: zero error, zero Jacobian.
        let mut j = [1.0; PATCH_PIXELS * 9];
        for x in [
            -world,
            Vector3::new((1.5 - CAMERA.cx) * z / CAMERA.fx, 0.0, z),
        ] {
            f.evaluate(&[&pose, &Point3(x)], &mut e, Some(&mut j))
                .unwrap();
            assert!(e.iter().chain(j.iter()).all(|&v| v == 0.0));
        }
    }
}
