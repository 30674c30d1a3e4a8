//! The `snavely_camera` kind: BAL's camera.

use std::any::Any;

use nalgebra::Vector3;

use super::{encode_as, Shape, Variable, VariableWire};
use crate::geometry::{so3, SnavelyCamera};

/// `snavely_camera` on the wire: BAL's nine parameters `[rx, ry, rz, tx, ty, tz, f, k1, k2]`
/// (angle-axis rotation).
pub const WIRE: VariableWire = VariableWire {
    kind: "snavely_camera",
    len: 9,
    components: &["rx", "ry", "rz", "tx", "ty", "tz", "f", "k1", "k2"],
    decode: |v| {
        let p: [f64; 9] = v
            .try_into()
            .map_err(|_| format!("expected 9 numbers, got {}", v.len()))?;
        Ok(Box::new(SnavelyCamera::from_bal(&p)))
    },
    encode: |v, out| encode_as::<SnavelyCamera, 9>(v, out, SnavelyCamera::to_bal),
    shape: Shape::Pose,
};

/// The BAL camera: rotation on SO(3) perturbed on the left, the rest additive:
/// `(R, t, f, k1, k2) ⊕ (ω, v, δf, δk1, δk2) = (Exp(ω) R, t + v, f + δf, k1 + δk1, k2 + δk2)`.
/// Tangent order: rotation, translation, f, k1, k2 (BAL's parameter order).
impl Variable for SnavelyCamera {
    fn kind(&self) -> &'static str {
        WIRE.kind
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
