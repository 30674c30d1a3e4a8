//! An exact solve lands: what it changed of the estimate clients were given is published, the
//! provisional values it now covers replaced by its own, and the size of that correction
//! recorded.

use std::sync::Arc;

use super::Latency;
use crate::api::latency::Correction;
use crate::api::wire::VariableValue;
use crate::problem::Problem;
use crate::session::mirror::{self, MirrorEntry, MovedValues};
use crate::session::{Session, State};

/// Refreshes the mirror from the exact solve of `sequence` (`moved`: the values it may have
/// changed, encoded before the lock was taken), as `mirror::refresh_observed` does; in a
/// session with a latency budget it also rewrites every provisional value the problem now
/// holds an exact one for, and records the correction.
pub(in crate::session) fn refresh_landing(
    st: &mut State,
    problem: &Problem,
    moved: &MovedValues,
    sequence: u64,
) -> Vec<VariableValue> {
    let Some(latency) = st.latency.as_mut() else {
        return mirror::refresh_observed(&mut st.mirror.entries, moved, sequence, &mut |_, _| {});
    };
    let entries = &mut st.mirror.entries;
    // Provisional values the exact solve covers: refreshed whether it moved them or not.
    let mut covered = Vec::new();
    latency.provisional.retain(|&key, &mut answered| {
        let Some(idx) = problem.values.index_of(key) else {
            return true;
        };
        if let Some(entry) = entries.get_mut(&key) {
            // Unless a client's guess came after the answer (applied next, as in
            // `mirror::refresh_observed`).
            if entry.changed == answered {
                entry.changed = entry.changed.min(sequence);
                covered.push((idx, key));
            }
        }
        false
    });
    let measuring = !covered.is_empty();
    // The few covered values the solve did not move: encoded here, under the lock.
    let unmoved: Vec<usize> = covered
        .iter()
        .filter(|&&(_, key)| !moved.contains(key))
        .map(|&(idx, _)| idx)
        .collect();
    let unmoved = MovedValues::encode(problem, Some(&unmoved));
    let (mut squares, mut max, mut count) = (0.0, 0.0f64, 0usize);
    let mut observe = |old: &MirrorEntry, new: &[f64]| {
        let d2 = position_change_squared(old, new);
        squares += d2;
        max = max.max(d2.sqrt());
        count += usize::from(d2 > 0.0);
    };
    let mut changed = mirror::refresh_observed(entries, moved, sequence, &mut observe);
    changed.extend(mirror::refresh_observed(
        entries,
        &unmoved,
        sequence,
        &mut observe,
    ));
    // A covered value that changed carries the newest sequence, so that a reader asking for
    // what changed since its provisional answer sees the correction.
    let newest = st.mirror.sequence;
    for (_, key) in &covered {
        if let Some(entry) = entries.get_mut(key) {
            if entry.changed == sequence {
                entry.changed = newest;
            }
        }
    }
    if measuring {
        let positioned = problem.values.len().max(1);
        latency.record_correction(Correction {
            sequence,
            rmse: (squares / positioned as f64).sqrt(),
            max,
            moved: count,
        });
    }
    latency
        .window
        .settle(st.results.solved_sequence.max(sequence));
    changed
}

/// The squared change of a variable's position (the first 2 or 3 numbers of the pose and point
/// kinds' wire values); 0 for kinds without one.
fn position_change_squared(old: &MirrorEntry, new: &[f64]) -> f64 {
    let dims = match old.kind {
        "se2" | "point2" => 2,
        "se3" | "point3" => 3,
        _ => 0,
    };
    old.value
        .iter()
        .zip(new)
        .take(dims)
        .map(|(a, b)| (a - b) * (a - b))
        .sum()
}

impl Session {
    /// After an exact solve landed and the batches that waited for it were applied: the
    /// variables it does not cover yet are answered again against it.
    pub(in crate::session) fn answer_after_landing(self: &Arc<Self>, st: &State) {
        let behind = st
            .latency
            .as_ref()
            .is_some_and(|l| l.answered > st.results.solved_sequence);
        if behind {
            self.spawn_provisional_answer(st.mirror.sequence, std::time::Duration::ZERO, true);
        }
    }
}

impl Latency {
    /// Whether an answer of `sequence` is still to be given.
    pub(super) fn unanswered(&self, sequence: u64, exact: u64) -> bool {
        sequence > exact && sequence > self.answered
    }
}
