//! The `se2` kind: a planar pose.

use std::any::Any;

use super::{encode_as, Shape, Variable, VariableWire};
use crate::geometry::{wrap_angle, Se2};

/// `se2` on the wire: `[x, y, θ]`, θ in radians, wrapped into (−π, π] on decoding.
pub const WIRE: VariableWire = VariableWire {
    kind: "se2",
    len: 3,
    components: &["x", "y", "theta"],
    decode: |v| Ok(Box::new(Se2::new(v[0], v[1], wrap_angle(v[2])))),
    encode: |v, out| encode_as::<Se2, 3>(v, out, Se2::to_array),
    shape: Shape::Pose,
};

/// SE(2) retraction is additive on (x, y, θ) with θ re-wrapped, as in g2o's `VertexSE2` and the
/// course; the between-factor Jacobians below are derived for exactly this retraction.
impl Variable for Se2 {
    fn kind(&self) -> &'static str {
        WIRE.kind
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
