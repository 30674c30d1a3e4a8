//! The `point3` kind: a landmark.

use std::any::Any;

use nalgebra::Vector3;

use super::{encode_as, Shape, Variable, VariableWire};
use crate::geometry::Point3;

/// `point3` on the wire: `[x, y, z]`.
pub const WIRE: VariableWire = VariableWire {
    kind: "point3",
    len: 3,
    components: &["x", "y", "z"],
    decode: |v| Ok(Box::new(Point3(Vector3::new(v[0], v[1], v[2])))),
    encode: |v, out| encode_as::<Point3, 3>(v, out, |p| p.0.into()),
    shape: Shape::Landmark,
};

/// A 3D point, additive.
impl Variable for Point3 {
    fn kind(&self) -> &'static str {
        WIRE.kind
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
