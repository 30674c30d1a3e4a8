//! An exact solve lands: what it changed of the estimate clients were given is published, the
//! provisional values it now covers replaced by its own, and the size of that correction
//! recorded.

use std::sync::{Arc, MutexGuard};

use super::Latency;
use crate::api::latency::Correction;
use crate::api::wire::{Estimate, SessionEvent, VariableValue, WireValue};
use crate::problem::{Key, Problem};
use crate::session::mirror::{self, MirrorEntry, MovedValues};
use crate::session::{Session, State};

/// How many mirror entries (walking it) or moved values (looking them up) a landing looks at per
/// hold of the session lock. Each costs 50-100 ns: a loop closure into a 30 000-pose 3D map
/// moves all of them, and written in one hold the lock was held 2-3.7 ms while the request path
/// waited for it (the provisional answer of a budgeted session, whose solve the landing then
/// also invalidated); in a 100 000-pose map, a correction scattered over it walked most of the
/// map. A slice holds it 0.1-0.5 ms.
const LANDING_SLICE: usize = 4096;

/// An exact solve of `sequence` written into the mirror, as `mirror::refresh_observed` does
/// (`moved`: the values it may have changed, encoded before the lock was taken): slice by slice
/// before the landing, each under its own hold of the lock ([`LandingRefresh::slice`]), and
/// what is left (at most a slice) with the landing ([`LandingRefresh::finish`]), which in a
/// session with a latency budget also rewrites every provisional value the problem now holds an
/// exact one for and records the correction. A small map or a small correction is written in
/// the landing's one hold, as before.
///
/// Between slices, batches are accepted and provisional answers given against a mirror partly
/// refreshed. That is safe as it is while the solve runs: a value a batch or an answer set
/// after the solve's sequence is newer and stays (the refresh skips it), and an answer given
/// meanwhile is answered again once the solve has landed (`answer_after_landing`). Each slice's
/// changed values go out in an `estimate` event of their own, so subscribers see the values in
/// the order the mirror took them.
pub(in crate::session) struct LandingRefresh<'a> {
    moved: &'a MovedValues,
    sequence: u64,
    /// Values written so far.
    done: usize,
    /// Whether the refresh walks the mirror or looks each value up (decided at the first slice).
    walk: Option<bool>,
    correction: CorrectionSum,
}

/// What the landing changed of the positions clients were given: the sum of squares, the
/// largest change and how many changed.
#[derive(Default)]
struct CorrectionSum {
    squares: f64,
    max: f64,
    count: usize,
}

impl CorrectionSum {
    fn observe(&mut self, old: &MirrorEntry, new: &[f64]) {
        let d2 = position_change_squared(old, new);
        self.squares += d2;
        self.max = self.max.max(d2.sqrt());
        self.count += usize::from(d2 > 0.0);
    }
}

impl<'a> LandingRefresh<'a> {
    pub fn new(moved: &'a MovedValues, sequence: u64) -> Self {
        Self {
            moved,
            sequence,
            done: 0,
            walk: None,
            correction: CorrectionSum::default(),
        }
    }

    /// The sequence of the solve it writes.
    pub fn sequence(&self) -> u64 {
        self.sequence
    }

    /// Writes the next slice into `st`'s mirror and returns what changed (for an `estimate`
    /// event); `None` when what is left is the landing's own (nothing, or no more than a slice).
    pub fn slice(&mut self, st: &mut State) -> Option<Vec<VariableValue>> {
        let left = self.moved.values().len() - self.done;
        // A walk looks at the mirror between the first and the last key left: at most all of it.
        let work_left = match (left, self.walks(st)) {
            (0, _) => 0,
            (_, true) => st.mirror.entries.len(),
            (_, false) => left,
        };
        if work_left <= LANDING_SLICE {
            return None;
        }
        Some(self.refresh(st, LANDING_SLICE))
    }

    fn walks(&mut self, st: &State) -> bool {
        let entries = st.mirror.entries.len();
        *self.walk.get_or_insert_with(|| self.moved.walks(entries))
    }

    /// Writes what is left, looking at no more than `at_most` entries or values; returns what
    /// changed.
    fn refresh(&mut self, st: &mut State, at_most: usize) -> Vec<VariableValue> {
        let walk = self.walks(st);
        let values = &self.moved.values()[self.done..];
        let correction = &mut self.correction;
        let (changed, done) = mirror::refresh_observed(
            &mut st.mirror.entries,
            values,
            walk,
            at_most,
            self.sequence,
            &mut |old, new| correction.observe(old, new),
        );
        self.done += done;
        changed
    }

    /// What is left, and in a session with a latency budget the provisional values the solve
    /// covers; returns what changed.
    pub fn finish(mut self, st: &mut State, problem: &Problem) -> Vec<VariableValue> {
        let sequence = self.sequence;
        // Provisional values the exact solve covers (none without a budget): refreshed whether
        // it moved them or not.
        let covered = take_covered(st, problem, sequence);
        let mut changed = self.refresh(st, usize::MAX);
        if !covered.is_empty() {
            changed.extend(self.refresh_covered(st, problem, &covered));
        }
        let solved = st.results.solved_sequence.max(sequence);
        if let Some(latency) = st.latency.as_mut() {
            if !covered.is_empty() {
                let CorrectionSum {
                    squares,
                    max,
                    count,
                } = self.correction;
                let positioned = problem.values.len().max(1);
                latency.record_correction(Correction {
                    sequence,
                    rmse: (squares / positioned as f64).sqrt(),
                    max,
                    moved: count,
                });
            }
            latency.window.settle(solved);
        }
        changed
    }

    /// The covered provisional values written again: those an earlier slice skipped (their
    /// answer was newer than the solve's sequence) from what the solve moved, the few it did not
    /// move encoded here, under the lock. Each that changed carries the newest sequence, so that
    /// a reader asking for what changed since its provisional answer sees the correction.
    fn refresh_covered(
        &mut self,
        st: &mut State,
        problem: &Problem,
        covered: &[(usize, Key)],
    ) -> Vec<VariableValue> {
        let mut values: Vec<(Key, WireValue)> = Vec::with_capacity(covered.len());
        let mut unmoved = Vec::new();
        for &(idx, key) in covered {
            match self.moved.get(key) {
                Some(value) => values.push((key, value.clone())),
                None => unmoved.push(idx),
            }
        }
        values.extend(MovedValues::encode(problem, Some(&unmoved)).into_values());
        values.sort_unstable_by_key(|&(key, _)| key);
        let correction = &mut self.correction;
        let (changed, _) = mirror::refresh_observed(
            &mut st.mirror.entries,
            &values,
            false,
            usize::MAX,
            self.sequence,
            &mut |old, new| correction.observe(old, new),
        );
        let newest = st.mirror.sequence;
        for (_, key) in covered {
            if let Some(entry) = st.mirror.entries.get_mut(key) {
                if entry.changed == self.sequence {
                    entry.changed = newest;
                }
            }
        }
        changed
    }
}

/// Takes the provisional values the exact solve of `sequence` covers (the problem holds the
/// variable) out of the session's provisional set, and marks those whose answer is still in the
/// mirror (no client's guess came after it) for the refresh; returns the marked ones.
fn take_covered(st: &mut State, problem: &Problem, sequence: u64) -> Vec<(usize, Key)> {
    let mut covered = Vec::new();
    let (Some(latency), entries) = (st.latency.as_mut(), &mut st.mirror.entries) else {
        return covered;
    };
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
    covered
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
    /// What a solve moved written into the mirror a slice per hold of the lock (see
    /// [`LandingRefresh`]), each slice in its own `estimate` event, with whoever waits for the
    /// lock let in between; returns the lock held for the landing, with what is left (at most a
    /// slice) for it.
    pub(in crate::session) fn refresh_before_landing(
        &self,
        refresh: &mut LandingRefresh<'_>,
    ) -> MutexGuard<'_, State> {
        loop {
            let mut st = self.lock();
            let Some(changed) = refresh.slice(&mut st) else {
                return st;
            };
            if !changed.is_empty() {
                self.emit(SessionEvent::Estimate(Estimate {
                    session: self.name.clone(),
                    sequence: refresh.sequence(),
                    variables: changed,
                }));
            }
            drop(st);
            self.state.let_waiters_in();
        }
    }

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
