//! Planar rigid motions (x, y, θ).

use super::so2::{rotation, wrap_angle};

/// A planar pose: translation `(x, y)` and heading `theta` in (−π, π].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Se2 {
    pub x: f64,
    pub y: f64,
    pub theta: f64,
}

impl Se2 {
    pub fn new(x: f64, y: f64, theta: f64) -> Self {
        Self {
            x,
            y,
            theta: wrap_angle(theta),
        }
    }

    pub fn identity() -> Self {
        Self::new(0.0, 0.0, 0.0)
    }

    /// `self ∘ other`: `other` expressed in the frame of `self`, brought to the world.
    pub fn compose(&self, other: &Se2) -> Se2 {
        let r = rotation(self.theta);
        Se2::new(
            self.x + r[0][0] * other.x + r[0][1] * other.y,
            self.y + r[1][0] * other.x + r[1][1] * other.y,
            self.theta + other.theta,
        )
    }

    pub fn inverse(&self) -> Se2 {
        let (s, c) = self.theta.sin_cos();
        Se2::new(
            -(c * self.x + s * self.y),
            s * self.x - c * self.y,
            -self.theta,
        )
    }

    /// `self⁻¹ ∘ other`, the pose of `other` seen from `self`.
    pub fn between(&self, other: &Se2) -> Se2 {
        self.inverse().compose(other)
    }

    /// Exponential map of the tangent `(v_x, v_y, ω)` (true SE(2) exp, with the V(ω) coupling).
    pub fn exp(tangent: [f64; 3]) -> Se2 {
        let [vx, vy, w] = tangent;
        let (s, c) = w.sin_cos();
        // V = [[a, -b], [b, a]] with a = sin ω/ω, b = (1 − cos ω)/ω; Taylor series near 0.
        let (a, b) = if w.abs() < 1e-6 {
            (1.0 - w * w / 6.0, w / 2.0 - w * w * w / 24.0)
        } else {
            (s / w, (1.0 - c) / w)
        };
        Se2::new(a * vx - b * vy, b * vx + a * vy, w)
    }

    /// Logarithm: the inverse of [`Se2::exp`]. Safe at θ = 0 and at θ = π.
    pub fn log(&self) -> [f64; 3] {
        let w = self.theta;
        // V⁻¹ = (1/(a² + b²)) [[a, b], [-b, a]]; with half-angle identities this is
        // [[h, w/2], [-w/2, h]] where h = (w/2)·cot(w/2), which is finite on (−π, π].
        let half = 0.5 * w;
        let h = if w.abs() < 1e-6 {
            1.0 - w * w / 12.0
        } else {
            half * half.cos() / half.sin()
        };
        [h * self.x + half * self.y, -half * self.x + h * self.y, w]
    }

    pub fn to_array(&self) -> [f64; 3] {
        [self.x, self.y, self.theta]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    #[test]
    fn exp_log_round_trip_including_pi() {
        for &w in &[0.0, 1e-9, 1e-4, 0.3, -2.0, PI - 1e-9, PI] {
            let t = [0.7, -1.3, w];
            let back = Se2::exp(t).log();
            for k in 0..3 {
                assert!((back[k] - t[k]).abs() < 1e-9, "w={w} {back:?}");
            }
        }
    }

    #[test]
    fn compose_inverse_is_identity() {
        let a = Se2::new(1.0, 2.0, 3.0);
        let id = a.compose(&a.inverse());
        assert!(id.x.abs() < 1e-12 && id.y.abs() < 1e-12 && id.theta.abs() < 1e-12);
        let b = Se2::new(-0.5, 0.25, -3.1);
        let ab = a.between(&b);
        let back = a.compose(&ab);
        assert!((back.x - b.x).abs() < 1e-12 && (back.y - b.y).abs() < 1e-12);
        assert!(wrap_angle(back.theta - b.theta).abs() < 1e-12);
    }
}
