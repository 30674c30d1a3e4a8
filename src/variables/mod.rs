//! Variables: anything with a tangent space and a retraction `x ⊕ δ`.
//!
//! The solver only ever asks a variable for its tangent dimension and to retract; factors downcast
//! to the concrete kind they need. New kinds (points, cameras, navigation states) implement this
//! trait in their own file and the solver does not change.
//!
//! Layer 1: imports only `geometry`.

use std::any::Any;
use std::fmt::Debug;

use nalgebra::Vector3;

use crate::geometry::{so3, wrap_angle, NavState, Point3, Se2, Se3, SnavelyCamera};

/// Variables are addressed by a 64-bit key chosen by the client (g2o vertex ids, say).
pub type Key = u64;

pub trait Variable: Any + Debug + Send + Sync {
    /// Short stable name, used in errors and on the wire (`"se2"`, `"se3"`).
    fn kind(&self) -> &'static str;
    fn tangent_dim(&self) -> usize;
    /// `self ← self ⊕ delta`, with `delta.len() == tangent_dim()`.
    fn retract(&mut self, delta: &[f64]);
    fn clone_box(&self) -> Box<dyn Variable>;
    /// Overwrites `self` with `other` without allocating; `false` if the kinds differ.
    fn assign_from(&mut self, other: &dyn Variable) -> bool;
    fn is_finite(&self) -> bool;
    fn as_any(&self) -> &dyn Any;
    /// The inverse of the retraction: `δ` with `origin ⊕ δ = self`, written to `out`
    /// (`tangent_dim()` long). `false` when this kind does not provide it or `origin` is of
    /// another kind. Marginalisation priors need it for the variables they touch.
    fn local(&self, _origin: &dyn Variable, _out: &mut [f64]) -> bool {
        false
    }
    /// Where it is in the world, for drawing: a pose's origin, a camera's centre, a point.
    fn position(&self) -> Option<[f64; 3]> {
        None
    }
}

/// `clone_box`, `assign_from` and `as_any`, the same for every `Copy` variable kind.
macro_rules! copy_variable_plumbing {
    () => {
        fn clone_box(&self) -> Box<dyn Variable> {
            Box::new(*self)
        }
        fn assign_from(&mut self, other: &dyn Variable) -> bool {
            match other.as_any().downcast_ref::<Self>() {
                Some(o) => {
                    *self = *o;
                    true
                }
                None => false,
            }
        }
        fn as_any(&self) -> &dyn Any {
            self
        }
    };
}

/// SE(2) retraction is additive on (x, y, θ) with θ re-wrapped, as in g2o's `VertexSE2` and the
/// course; the between-factor Jacobians below are derived for exactly this retraction.
impl Variable for Se2 {
    fn kind(&self) -> &'static str {
        "se2"
    }
    fn tangent_dim(&self) -> usize {
        3
    }
    fn retract(&mut self, delta: &[f64]) {
        self.x += delta[0];
        self.y += delta[1];
        self.theta = wrap_angle(self.theta + delta[2]);
    }
    fn is_finite(&self) -> bool {
        self.x.is_finite() && self.y.is_finite() && self.theta.is_finite()
    }
    fn position(&self) -> Option<[f64; 3]> {
        Some([self.x, self.y, 0.0])
    }
    copy_variable_plumbing!();
}

/// SE(3) retraction on the right, translation in the body frame:
/// `(R, t) ⊕ (v, ω) = (R Exp(ω), t + R v)`. Tangent order is (v, ω), the g2o files' (t, R) order.
impl Variable for Se3 {
    fn kind(&self) -> &'static str {
        "se3"
    }
    fn tangent_dim(&self) -> usize {
        6
    }
    fn retract(&mut self, delta: &[f64]) {
        let v = Vector3::new(delta[0], delta[1], delta[2]);
        let w = Vector3::new(delta[3], delta[4], delta[5]);
        self.translation += self.rotation * v;
        self.rotation *= so3::exp(&w);
        self.rotation.renormalize();
    }
    fn is_finite(&self) -> bool {
        self.translation.iter().all(|v| v.is_finite())
            && self.rotation.coords.iter().all(|v| v.is_finite())
    }
    fn position(&self) -> Option<[f64; 3]> {
        Some(self.translation.into())
    }
    copy_variable_plumbing!();
}

/// The BAL camera: rotation on SO(3) perturbed on the left, the rest additive:
/// `(R, t, f, k1, k2) ⊕ (ω, v, δf, δk1, δk2) = (Exp(ω) R, t + v, f + δf, k1 + δk1, k2 + δk2)`.
/// Tangent order: rotation, translation, f, k1, k2 (BAL's parameter order).
impl Variable for SnavelyCamera {
    fn kind(&self) -> &'static str {
        "snavely_camera"
    }
    fn tangent_dim(&self) -> usize {
        9
    }
    fn retract(&mut self, delta: &[f64]) {
        let w = Vector3::new(delta[0], delta[1], delta[2]);
        self.rotation = so3::exp(&w) * self.rotation;
        self.rotation.renormalize();
        self.translation += Vector3::new(delta[3], delta[4], delta[5]);
        self.focal += delta[6];
        self.k1 += delta[7];
        self.k2 += delta[8];
    }
    fn is_finite(&self) -> bool {
        self.translation.iter().all(|v| v.is_finite())
            && self.rotation.coords.iter().all(|v| v.is_finite())
            && [self.focal, self.k1, self.k2].iter().all(|v| v.is_finite())
    }
    fn position(&self) -> Option<[f64; 3]> {
        Some(self.centre().into())
    }
    copy_variable_plumbing!();
}

/// A 3D point, additive.
impl Variable for Point3 {
    fn kind(&self) -> &'static str {
        "point3"
    }
    fn tangent_dim(&self) -> usize {
        3
    }
    fn retract(&mut self, delta: &[f64]) {
        self.0 += Vector3::new(delta[0], delta[1], delta[2]);
    }
    fn is_finite(&self) -> bool {
        self.0.iter().all(|v| v.is_finite())
    }
    fn position(&self) -> Option<[f64; 3]> {
        Some(self.0.into())
    }
    copy_variable_plumbing!();
}

/// The sliding-window state; see [`NavState`] for the retraction.
impl Variable for NavState {
    fn kind(&self) -> &'static str {
        "nav_state"
    }
    fn tangent_dim(&self) -> usize {
        15
    }
    fn retract(&mut self, delta: &[f64]) {
        NavState::retract(self, delta);
    }
    fn is_finite(&self) -> bool {
        NavState::is_finite(self)
    }
    fn position(&self) -> Option<[f64; 3]> {
        Some(self.position.into())
    }
    fn local(&self, origin: &dyn Variable, out: &mut [f64]) -> bool {
        match origin.as_any().downcast_ref::<NavState>() {
            Some(origin) => {
                out.copy_from_slice(NavState::local(self, origin).as_slice());
                true
            }
            None => false,
        }
    }
    copy_variable_plumbing!();
}
