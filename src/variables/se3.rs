//! The `se3` kind: a pose in space.

use std::any::Any;

use nalgebra::{Quaternion, Vector3};

use super::{encode_as, Shape, Variable, VariableWire};
use crate::geometry::{so3, Se3};

/// `se3` on the wire: `[x, y, z, qx, qy, qz, qw]` (g2o order); the quaternion must have unit
/// norm within 1e-3 and is normalised. Factor measurements of poses use the same encoding.
pub const WIRE: VariableWire = VariableWire {
    kind: "se3",
    len: 7,
    components: &["x", "y", "z", "qx", "qy", "qz", "qw"],
    decode: |v| Ok(Box::new(decode_se3(v)?)),
    encode: |v, out| {
        encode_as::<Se3, 7>(v, out, |p| {
            let q = p.rotation.quaternion();
            let t = p.translation;
            [t.x, t.y, t.z, q.i, q.j, q.k, q.w]
        })
    },
    shape: Shape::Pose,
};

/// Decodes `[x, y, z, qx, qy, qz, qw]` (length checked by the caller), refusing a quaternion
/// whose norm is not 1 within [`so3::UNIT_NORM_TOLERANCE`].
pub fn decode_se3(v: &[f64]) -> Result<Se3, String> {
    let q = Quaternion::new(v[6], v[3], v[4], v[5]);
    let rotation = so3::unit_within_tolerance(q)
        .map_err(|norm| format!("quaternion (qx, qy, qz, qw) has norm {norm}, expected 1"))?;
    Ok(Se3::new(rotation, Vector3::new(v[0], v[1], v[2])))
}

/// SE(3) retraction on the right, translation in the body frame:
/// `(R, t) ⊕ (v, ω) = (R Exp(ω), t + R v)`. Tangent order is (v, ω), the g2o files' (t, R) order.
impl Variable for Se3 {
    fn kind(&self) -> &'static str {
        WIRE.kind
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
