//! The `nav_state` kind of the sliding window; built by the window itself, never sent as a batch
//! variable, so it has no wire declaration.

use std::any::Any;

use super::Variable;
use crate::geometry::NavState;

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
