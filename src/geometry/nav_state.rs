//! The 15-dof navigation state of sliding-window fusion: position, rotation (body to world),
//! velocity in the world, accelerometer and gyroscope biases.
//!
//! Tangent order `(δp, δθ, δv, δb_a, δb_g)`, retraction
//! `(p, R, v, b_a, b_g) ⊕ δ = (p + δp, R Exp(δθ), v + δv, b_a + δb_a, b_g + δb_g)`:
//! rotation perturbed on the right (in the body frame), everything else additive, as in the
//! course's sliding-window back-end.

use nalgebra::{UnitQuaternion, Vector3};

use super::{so3, Se3};

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NavState {
    pub position: Vector3<f64>,
    pub rotation: UnitQuaternion<f64>,
    pub velocity: Vector3<f64>,
    pub accel_bias: Vector3<f64>,
    pub gyro_bias: Vector3<f64>,
}

/// Offsets of the blocks in the 15-dim tangent space.
pub const P: usize = 0;
pub const THETA: usize = 3;
pub const V: usize = 6;
pub const BA: usize = 9;
pub const BG: usize = 12;

impl NavState {
    /// At rest at `pose`, unbiased.
    pub fn at_pose(pose: &Se3) -> Self {
        Self {
            position: pose.translation,
            rotation: pose.rotation,
            velocity: Vector3::zeros(),
            accel_bias: Vector3::zeros(),
            gyro_bias: Vector3::zeros(),
        }
    }

    pub fn pose(&self) -> Se3 {
        Se3::new(self.rotation, self.position)
    }

    pub fn retract(&mut self, delta: &[f64]) {
        let block = |k: usize| Vector3::new(delta[k], delta[k + 1], delta[k + 2]);
        self.position += block(P);
        self.rotation *= so3::exp(&block(THETA));
        self.rotation.renormalize();
        self.velocity += block(V);
        self.accel_bias += block(BA);
        self.gyro_bias += block(BG);
    }

    /// `δ` with `origin ⊕ δ = self`: the inverse of [`NavState::retract`].
    pub fn local(&self, origin: &NavState) -> nalgebra::SVector<f64, 15> {
        let mut delta = nalgebra::SVector::<f64, 15>::zeros();
        let mut put = |k: usize, v: Vector3<f64>| delta.fixed_rows_mut::<3>(k).copy_from(&v);
        put(P, self.position - origin.position);
        put(
            THETA,
            so3::log(&(origin.rotation.inverse() * self.rotation)),
        );
        put(V, self.velocity - origin.velocity);
        put(BA, self.accel_bias - origin.accel_bias);
        put(BG, self.gyro_bias - origin.gyro_bias);
        delta
    }

    pub fn is_finite(&self) -> bool {
        [
            &self.position,
            &self.velocity,
            &self.accel_bias,
            &self.gyro_bias,
        ]
        .iter()
        .all(|v| v.iter().all(|x| x.is_finite()))
            && self.rotation.coords.iter().all(|x| x.is_finite())
    }
}
