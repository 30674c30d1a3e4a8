//! A merge applied to the problem: the moved component's values move, the agreeing closures
//! enter, and the mirror takes the moved values from the problem (the problem may have come
//! back from a solve since the mirror moved them).

use std::collections::BTreeMap;

use super::Merge;
use crate::api::catalogue;
use crate::api::wire::{FactorId, WireValue};
use crate::problem::{Key, Problem};
use crate::session::MirrorEntry;

/// Applies `merges` to `problem` (whose factors have `ids`); returns the keys that moved.
pub(crate) fn apply_to_problem(
    problem: &mut Problem,
    ids: &mut Vec<FactorId>,
    merges: Vec<Merge>,
) -> Vec<Key> {
    let mut moved = Vec::new();
    for merge in merges {
        for &key in &merge.moved_keys {
            if let Some(idx) = problem.values.index_of(key) {
                merge.frame.apply(problem.values.variable_mut(idx));
                moved.push(key);
            }
        }
        for (id, f) in merge.closures {
            // Checked when its batch was accepted, like every factor of a batch.
            problem
                .add_checked_factor_sqrt(f.factor, f.sqrt_information, f.robust, String::new())
                .expect("validated when accepted");
            ids.push(id);
        }
    }
    moved
}

/// The mirror's values of `keys` from the problem.
pub(crate) fn resync_mirror(
    problem: &Problem,
    mirror: &mut BTreeMap<Key, MirrorEntry>,
    keys: &[Key],
) {
    for key in keys {
        if let (Some(v), Some(entry)) = (problem.values.get(*key), mirror.get_mut(key)) {
            entry.value = WireValue::from_vec(catalogue::encode_variable(v));
        }
    }
}
