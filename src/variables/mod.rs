//! Variables: anything with a tangent space and a retraction `x ⊕ δ`.
//!
//! The solver only ever asks a variable for its tangent dimension and to retract; factors downcast
//! to the concrete kind they need. New kinds (points, cameras, navigation states) implement this
//! trait in their own file and the solver does not change.
//!
//! Each kind lives in its own file with its [`VariableWire`]: the one declaration of how that kind
//! travels on the wire (its name, length, encoding and how the web view draws it). The api
//! catalogue only lists these declarations.
//!
//! Layer 1: imports only `geometry`.

use std::any::Any;
use std::fmt::Debug;

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

/// The covariance of `variable`'s [`Variable::position`] in the world, 3×3 row-major, from
/// the covariance of its tangent (`tangent_dim()`² row-major): `J Σ Jᵀ`, with `J` the
/// position's derivative along the retraction, by central differences (positions are smooth
/// in the tangent, and linear in it for every kind but a camera's centre). What covariance
/// ellipses are drawn from, whatever the kind's tangent frame (an `se3`'s is the body's).
/// `None` for a kind without a position or a covariance of the wrong size.
pub fn position_covariance(variable: &dyn Variable, covariance: &[f64]) -> Option<[f64; 9]> {
    const STEP: f64 = 1e-6;
    let n = variable.tangent_dim();
    variable.position()?;
    if covariance.len() != n * n {
        return None;
    }
    let moved = |i: usize, step: f64| {
        let mut delta = vec![0.0; n];
        delta[i] = step;
        let mut v = variable.clone_box();
        v.retract(&delta);
        v.position()
    };
    // J (3 × n), column by column; then J Σ Jᵀ.
    let mut jacobian = nalgebra::DMatrix::zeros(3, n);
    for i in 0..n {
        let (plus, minus) = (moved(i, STEP)?, moved(i, -STEP)?);
        for r in 0..3 {
            jacobian[(r, i)] = (plus[r] - minus[r]) / (2.0 * STEP);
        }
    }
    let sigma = nalgebra::DMatrix::from_row_slice(n, n, covariance);
    let world = &jacobian * sigma * jacobian.transpose();
    Some(std::array::from_fn(|k| world[(k / 3, k % 3)]))
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

// After the macro: the kinds' files use it.
pub mod frame;
pub mod nav_state;
pub mod point2;
pub mod point3;
pub mod se2;
pub mod se3;
pub mod snavely_camera;

/// Builds a variable from its wire encoding (length already checked), or says why not.
pub type DecodeVariable = fn(&[f64]) -> Result<Box<dyn Variable>, String>;

/// What a variable is when drawn: a pose of the trajectory or a landmark of a point cloud.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Shape {
    Pose,
    Landmark,
}

/// How one variable kind travels on the wire: declared once, next to the kind's `Variable` impl,
/// and listed by `api::catalogue`.
pub struct VariableWire {
    /// The kind's name, as [`Variable::kind`] returns it and clients write it.
    pub kind: &'static str,
    /// Number of values in the wire encoding.
    pub len: usize,
    /// The encoding's components in order, for documentation (`["x", "y", "theta"]`).
    pub components: &'static [&'static str],
    pub decode: DecodeVariable,
    /// Writes the wire encoding to the vector (cleared first, so a caller can reuse one).
    pub encode: fn(&dyn Variable, &mut Vec<f64>),
    /// How the web view draws it.
    pub shape: Shape,
}

/// `out` cleared, then filled with `encode` applied to `v` downcast to the kind a codec was
/// chosen for.
pub(crate) fn encode_as<T: 'static, const N: usize>(
    v: &dyn Variable,
    out: &mut Vec<f64>,
    encode: impl Fn(&T) -> [f64; N],
) {
    let v = v
        .as_any()
        .downcast_ref::<T>()
        .expect("codec is chosen by the variable's kind");
    out.clear();
    out.extend_from_slice(&encode(v));
}

#[cfg(test)]
mod tests {
    use nalgebra::{UnitQuaternion, Vector3};

    use super::*;
    use crate::geometry::Se3;

    #[test]
    fn position_covariance_turns_a_body_frame_tangent_into_the_world() {
        // Yawed 90°: body x is world y.
        let pose = Se3::new(
            UnitQuaternion::from_euler_angles(0.0, 0.0, std::f64::consts::FRAC_PI_2),
            Vector3::new(1.0, 2.0, 3.0),
        );
        let mut tangent = [0.0; 36];
        for (i, variance) in [1.0, 4.0, 9.0, 0.1, 0.1, 0.1].iter().enumerate() {
            tangent[i * 7] = *variance;
        }
        let world = position_covariance(&pose, &tangent).expect("a pose has a position");
        let expected = [4.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 9.0];
        for (got, want) in world.iter().zip(expected) {
            assert!((got - want).abs() < 1e-6, "{world:?}");
        }
        assert_eq!(position_covariance(&pose, &tangent[..35]), None);
    }
}
