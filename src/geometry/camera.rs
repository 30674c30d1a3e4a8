//! The Snavely / Bundler camera of the BAL datasets, and 3D points.
//!
//! ```text
//! P  = R X + t                      world → camera
//! p  = −(P.x, P.y) / P.z            the camera looks down −z
//! p' = f (1 + k1 ‖p‖² + k2 ‖p‖⁴) p  pixels, origin at the image centre, y up
//! ```
//!
//! The BAL files store R as an angle-axis vector; it is kept here as a unit quaternion.

use nalgebra::{UnitQuaternion, Vector2, Vector3};

use super::so3;

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SnavelyCamera {
    pub rotation: UnitQuaternion<f64>,
    pub translation: Vector3<f64>,
    pub focal: f64,
    pub k1: f64,
    pub k2: f64,
}

/// A point in 3D.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Point3(pub Vector3<f64>);

/// A point in the plane (a 2D landmark).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Point2(pub nalgebra::Vector2<f64>);

impl SnavelyCamera {
    /// From BAL's nine parameters: angle-axis (3), translation (3), f, k1, k2.
    pub fn from_bal(p: &[f64; 9]) -> Self {
        Self {
            rotation: so3::exp(&Vector3::new(p[0], p[1], p[2])),
            translation: Vector3::new(p[3], p[4], p[5]),
            focal: p[6],
            k1: p[7],
            k2: p[8],
        }
    }

    /// Back to BAL's nine parameters.
    pub fn to_bal(&self) -> [f64; 9] {
        let r = so3::log(&self.rotation);
        let t = self.translation;
        [r.x, r.y, r.z, t.x, t.y, t.z, self.focal, self.k1, self.k2]
    }

    /// The point in the camera frame.
    pub fn to_camera(&self, x: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * x + self.translation
    }

    /// Pixel coordinates of a world point.
    pub fn project(&self, x: &Vector3<f64>) -> Vector2<f64> {
        let c = self.to_camera(x);
        let p = Vector2::new(-c.x / c.z, -c.y / c.z);
        let n = p.norm_squared();
        p * (self.focal * (1.0 + self.k1 * n + self.k2 * n * n))
    }

    /// The camera centre in the world: `−Rᵀ t`.
    pub fn centre(&self) -> Vector3<f64> {
        -(self.rotation.inverse() * self.translation)
    }
}
