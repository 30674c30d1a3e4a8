//! The `point2` kind: a landmark in the plane (2D landmark SLAM, e.g. Victoria Park's trees).

use std::any::Any;

use nalgebra::Vector2;

use super::{encode_as, Shape, Variable, VariableWire};
use crate::geometry::Point2;

/// `point2` on the wire: `[x, y]`.
pub const WIRE: VariableWire = VariableWire {
    kind: "point2",
    len: 2,
    components: &["x", "y"],
    decode: |v| Ok(Box::new(Point2(Vector2::new(v[0], v[1])))),
    encode: |v, out| encode_as::<Point2, 2>(v, out, |p| [p.0.x, p.0.y]),
    shape: Shape::Landmark,
};

/// A 2D point, additive.
impl Variable for Point2 {
    fn kind(&self) -> &'static str {
        WIRE.kind
    }
    fn tangent_dim(&self) -> usize {
        2
    }
    fn retract(&mut self, delta: &[f64]) {
        self.0 += Vector2::new(delta[0], delta[1]);
    }
    fn is_finite(&self) -> bool {
        self.0.iter().all(|v| v.is_finite())
    }
    fn position(&self) -> Option<[f64; 3]> {
        Some([self.0.x, self.0.y, 0.0])
    }
    copy_variable_plumbing!();
}
