//! The mirror: every accepted variable as clients see it (kind, wire value, when it changed),
//! kept apart from the problem so reads never wait for a solve that has the problem.

use std::collections::BTreeMap;

use super::batch::PreparedBatch;
use super::engine::Engine;
use super::state::Mirror;
use super::{inspect, Session};
use crate::api::catalogue;
use crate::api::export::{self, EstimateFormat, Export};
use crate::api::wire::{Estimate, EstimateQuery, FactorId, VariableValue};
use crate::api::ServiceError;
use crate::problem::{Key, Problem, Variable};

/// The mirror keeps values in their wire form, inline (see [`WireValue`]): after a loop closure
/// a solve compares and rewrites hundreds of them under the session lock, and with each value
/// in an allocation of its own every one cost a second cache miss (M3500 over HTTP: 6.6% of
/// the server's samples in that loop, most of them on the value's first load).
pub use crate::api::wire::WireValue;

/// The numbers of `value` kept on the heap (beyond the inline capacity), for memory accounting.
pub fn heap_values(value: &WireValue) -> usize {
    match value.spilled() {
        true => value.len(),
        false => 0,
    }
}

/// A variable as clients see it.
#[derive(Clone, Debug)]
pub struct MirrorEntry {
    pub kind: &'static str,
    pub value: WireValue,
    pub changed: u64,
    pub fixed: bool,
    /// Position of the value the client last sent (the web view's initial guess).
    pub initial: [f64; 3],
    /// When the pose was taken (seconds), as the client said when it created the variable.
    pub stamp: Option<f64>,
}

impl MirrorEntry {
    pub fn decode(&self) -> Box<dyn Variable> {
        let codec =
            catalogue::variable_codec(self.kind).expect("mirror kinds come from the catalogue");
        (codec.decode)(&self.value).expect("mirror values were encoded by the codec")
    }
}

impl Session {
    /// The variables `query` selects with the session's sequence. A window session has no
    /// variables of its own: its trajectory stands for them (see [`Session::export`]), in the
    /// key range; `since` selects none of it (trajectory states carry no change counter).
    pub fn estimate(&self, query: &EstimateQuery) -> Estimate {
        let range = query.from.unwrap_or(0)..=query.to.unwrap_or(Key::MAX);
        let (sequence, variables) = match &self.engine {
            Engine::Window(_) => {
                let variables = match query.since {
                    Some(_) => Vec::new(),
                    None => self.window_trajectory_in(&range),
                };
                (self.lock().mirror.sequence, variables)
            }
            Engine::Graph(_) => {
                let st = self.lock();
                let since = query.since.unwrap_or(0);
                let mut variables = if range.start() > range.end() {
                    Vec::new()
                } else {
                    st.mirror
                        .entries
                        .range(range)
                        .filter(|(_, e)| query.since.is_none() || e.changed > since)
                        .map(|(&k, e)| value_of(k, e))
                        .collect()
                };
                super::robots::in_robot_frame(&st, query, &mut variables);
                (st.mirror.sequence, variables)
            }
        };
        Estimate {
            session: self.name.clone(),
            sequence,
            variables,
        }
    }

    /// The estimate as a file (see `api::export`): a graph session's variables in the query's
    /// key range, or a window session's trajectory (smoothed keyframes, then the window).
    pub fn export(
        &self,
        format: EstimateFormat,
        query: &EstimateQuery,
    ) -> Result<Export, ServiceError> {
        let variables = match &self.engine {
            Engine::Graph(_) => self.estimate(query).variables,
            Engine::Window(_) => {
                let range = query.from.unwrap_or(0)..=query.to.unwrap_or(Key::MAX);
                self.window_trajectory_in(&range)
            }
        };
        Ok(export::render(&self.name, format, &variables))
    }

    fn window_trajectory_in(&self, range: &std::ops::RangeInclusive<Key>) -> Vec<VariableValue> {
        let mut trajectory = self
            .window_trajectory()
            .expect("only called for window sessions");
        trajectory.retain(|v| range.contains(&v.key));
        trajectory
    }
}

pub(super) fn value_of(key: Key, e: &MirrorEntry) -> VariableValue {
    VariableValue {
        key,
        kind: e.kind.into(),
        value: e.value.clone(),
        changed: e.changed,
        stamp: e.stamp,
    }
}

/// A refresh walks the mirror in key order instead of looking each variable up once it
/// covers at least this fraction (1/N) of the mirror.
const WALK_FROM_ONE_IN: usize = 8;

/// The wire values of the variables a solve may have moved, in key order, encoded from the
/// solved problem by the worker before it takes the session lock.
///
/// A loop closure in a 100 000-pose map moves 10 000–27 000 variables; encoding them (a
/// virtual call and a codec lookup each) under the lock held it 5.5–9 ms per landing, and
/// every batch arriving meanwhile waited. Under the lock only the walk, the comparison and the
/// copy remain (2.3–3.6 ms for 23 000–27 000 moved).
#[derive(Debug, Default)]
pub(super) struct MovedValues {
    values: Vec<(Key, WireValue)>,
}

impl MovedValues {
    /// The values of `moved` (dense indices into `problem`, in any order, repeats allowed;
    /// `None`: every variable).
    pub fn encode(problem: &Problem, moved: Option<&[usize]>) -> Self {
        let keys = problem.values.keys();
        let mut wanted: Vec<(Key, usize)> = match moved {
            Some(moved) => moved.iter().map(|&idx| (keys[idx], idx)).collect(),
            None => keys.iter().copied().zip(0..).collect(),
        };
        // Streams add keys in increasing order, so this is mostly sorted already.
        wanted.sort_unstable();
        wanted.dedup();
        let mut scratch = Vec::new();
        let values = wanted
            .into_iter()
            .map(|(key, idx)| {
                catalogue::encode_variable_into(problem.values.variable(idx), &mut scratch);
                (key, WireValue::from_slice(&scratch))
            })
            .collect();
        Self { values }
    }

    /// The value of `key`, if it is among them.
    pub fn get(&self, key: Key) -> Option<&WireValue> {
        let at = self.values.binary_search_by_key(&key, |(k, _)| *k).ok()?;
        Some(&self.values[at].1)
    }

    /// The values, in key order.
    pub fn values(&self) -> &[(Key, WireValue)] {
        &self.values
    }

    /// The values, in key order, taken out.
    pub fn into_values(self) -> Vec<(Key, WireValue)> {
        self.values
    }

    /// Whether a refresh of a mirror of `entries` walks it in key order rather than looking each
    /// value up: when they are at least a [`WALK_FROM_ONE_IN`]th of it (decided for the whole
    /// set, so that each slice of a landing decides alike).
    pub fn walks(&self, entries: usize) -> bool {
        self.values.len().saturating_mul(WALK_FROM_ONE_IN) >= entries
    }
}

/// Copies `values` (in key order) into the mirror, telling `observe` each entry it is about to
/// change (with its old value) and the new value, until it has looked at `at_most` entries
/// (walking the mirror) or values (looking them up); returns those that changed and how many of
/// `values` it is done with. Runs under the session lock, over every variable a loop closure
/// moved, so it allocates only for what it returns.
///
/// Looked up one by one in the `BTreeMap`, each variable cost a descent of cache misses (10k
/// stream in-process: 3–4 % of the samples in the lookup); in key order, most of a map is met
/// in one pass over its leaves (`walk`). A walk looks at every entry between the first value's
/// key and the last's, which for a correction scattered over a 100 000-pose map is most of it.
pub(super) fn refresh_observed(
    mirror: &mut BTreeMap<Key, MirrorEntry>,
    values: &[(Key, WireValue)],
    walk: bool,
    at_most: usize,
    sequence: u64,
    observe: &mut dyn FnMut(&MirrorEntry, &[f64]),
) -> (Vec<VariableValue>, usize) {
    let mut changed = Vec::new();
    let mut refresh_entry = |key: Key, value: &WireValue, entry: &mut MirrorEntry| {
        // A batch accepted during the solve set a newer guess; it is applied next.
        if entry.changed <= sequence && entry.value[..] != value[..] {
            observe(entry, value);
            entry.value.clone_from(value);
            entry.changed = sequence;
            changed.push(value_of(key, entry));
        }
    };
    if !walk {
        let done = values.len().min(at_most);
        for (key, value) in &values[..done] {
            if let Some(entry) = mirror.get_mut(key) {
                refresh_entry(*key, value, entry);
            }
        }
        return (changed, done);
    }
    let (Some((first, _)), Some((last, _))) = (values.first(), values.last()) else {
        return (changed, 0);
    };
    let mut wanted = values.iter().peekable();
    for (looked, (&key, entry)) in mirror.range_mut(*first..=*last).enumerate() {
        // Past the values before this entry (those the mirror lacks among them).
        while wanted.next_if(|(k, _)| *k < key).is_some() {}
        if looked == at_most {
            return (changed, values.len() - wanted.len());
        }
        if let Some((_, value)) = wanted.next_if(|(k, _)| *k == key) {
            refresh_entry(key, value, entry);
        }
    }
    (changed, values.len())
}

impl Mirror {
    /// Step 3 of accepting a batch: its variables, guesses, fixes and factors as clients see
    /// them, at `sequence`. Returns the values it set (for the `estimate` event).
    pub(super) fn accept(
        &mut self,
        prepared: &PreparedBatch,
        factor_ids: &[FactorId],
        sequence: u64,
    ) -> Vec<VariableValue> {
        let mut new_values = Vec::new();
        for v in &prepared.variables {
            let kind = v.value.kind();
            let value = WireValue::from_vec(catalogue::encode_variable(v.value.as_ref()));
            let entry = MirrorEntry {
                kind,
                initial: inspect::position(kind, &value),
                value,
                changed: sequence,
                fixed: v.fixed,
                stamp: v.stamp,
            };
            new_values.push(value_of(v.key, &entry));
            self.heap_values += heap_values(&entry.value);
            if let Some(old) = self.entries.insert(v.key, entry) {
                self.heap_values -= heap_values(&old.value);
            }
        }
        for (key, v) in &prepared.guesses {
            let value = WireValue::from_vec(catalogue::encode_variable(v.as_ref()));
            let added = heap_values(&value);
            let entry = self.entries.get_mut(key).expect("validated");
            let removed = heap_values(&entry.value);
            entry.initial = inspect::position(entry.kind, &value);
            entry.value = value;
            entry.changed = sequence;
            new_values.push(value_of(*key, entry));
            self.heap_values = self.heap_values + added - removed;
        }
        for &(key, fixed) in &prepared.fix {
            self.entries.get_mut(&key).expect("validated").fixed = fixed;
        }
        self.live_factors.extend(factor_ids.iter().copied());
        for (f, &id) in prepared.factors.iter().zip(factor_ids) {
            if let Some(edge) = inspect::edge(&self.entries, f.factor.keys()) {
                self.edges.insert(id, edge);
            }
        }
        for id in &prepared.remove {
            self.live_factors.remove(id);
            self.edges.remove(id);
        }
        new_values
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Se2;

    fn entry(value: &[f64], changed: u64) -> MirrorEntry {
        MirrorEntry {
            kind: "se2",
            value: value.iter().copied().collect(),
            changed,
            fixed: false,
            initial: [0.0; 3],
            stamp: None,
        }
    }

    /// A problem with keys `keys` (in that order of insertion) at x = key, and a mirror that
    /// holds them at x = 0, plus a key the problem does not have.
    fn setup(keys: &[Key]) -> (Problem, BTreeMap<Key, MirrorEntry>) {
        let mut problem = Problem::default();
        let mut mirror = BTreeMap::new();
        for &k in keys {
            problem
                .values
                .insert(k, Box::new(Se2::new(k as f64, 0.0, 0.0)))
                .expect("distinct keys");
            mirror.insert(k, entry(&[0.0, 0.0, 0.0], 1));
        }
        mirror.insert(1_000_000, entry(&[5.0, 0.0, 0.0], 1));
        (problem, mirror)
    }

    /// The values of `moved` (`None`: all) encoded and copied into the mirror.
    fn refresh(
        mirror: &mut BTreeMap<Key, MirrorEntry>,
        problem: &Problem,
        moved: Option<&[usize]>,
        sequence: u64,
    ) -> Vec<VariableValue> {
        let moved = MovedValues::encode(problem, moved);
        let walk = moved.walks(mirror.len());
        let (changed, done) = refresh_observed(
            mirror,
            moved.values(),
            walk,
            usize::MAX,
            sequence,
            &mut |_, _| {},
        );
        assert_eq!(done, moved.values().len());
        changed
    }

    fn refreshed(changed: &[VariableValue]) -> Vec<Key> {
        let mut keys: Vec<Key> = changed.iter().map(|v| v.key).collect();
        keys.sort_unstable();
        keys
    }

    #[test]
    fn both_paths_refresh_exactly_the_moved_entries() {
        // Keys not in insertion order, so that the walk has to sort them.
        let keys: Vec<Key> = (0..64).map(|i| (i * 37) % 64 + 1).collect();
        let moved: Vec<usize> = vec![3, 17, 3, 40];
        let expected: Vec<Key> = {
            let mut k: Vec<Key> = [3usize, 17, 40].iter().map(|&i| keys[i]).collect();
            k.sort_unstable();
            k
        };
        // A few moved of many: looked up; most of them: walked (duplicates once each).
        let few = &moved[..];
        let many: Vec<usize> = (0..60).chain([5, 5]).collect();
        // A variable of the problem the mirror does not hold is skipped.
        let unmirrored = keys[10];
        for (moved, walked) in [(few, false), (&many[..], true)] {
            let (problem, mut mirror) = setup(&keys);
            mirror.remove(&unmirrored);
            assert_eq!(
                moved.len() * WALK_FROM_ONE_IN >= mirror.len(),
                walked,
                "the case takes the intended path"
            );
            let changed = refresh(&mut mirror, &problem, Some(moved), 7);
            let want: Vec<Key> = match walked {
                false => expected.clone(),
                true => {
                    let mut k: Vec<Key> = (0..60)
                        .map(|i| keys[i])
                        .filter(|&k| k != unmirrored)
                        .collect();
                    k.sort_unstable();
                    k
                }
            };
            assert_eq!(refreshed(&changed), want);
            for (&key, e) in &mirror {
                let moved_here = want.contains(&key);
                let x = if moved_here {
                    key as f64
                } else if key == 1_000_000 {
                    5.0
                } else {
                    0.0
                };
                assert_eq!(e.value[0], x, "key {key}");
                assert_eq!(e.changed, if moved_here { 7 } else { 1 }, "key {key}");
            }
        }
    }

    #[test]
    fn a_full_refresh_skips_unchanged_and_newer_entries() {
        let keys: Vec<Key> = (1..=20).rev().collect();
        let (problem, mut mirror) = setup(&keys);
        // Already at its value: not reported. Set by a newer batch: left alone.
        mirror.insert(4, entry(&[4.0, 0.0, 0.0], 1));
        mirror.insert(9, entry(&[0.0, 0.0, 0.0], 8));
        let changed = refresh(&mut mirror, &problem, None, 7);
        let want: Vec<Key> = (1..=20).filter(|&k| k != 4 && k != 9).collect();
        assert_eq!(refreshed(&changed), want);
        assert_eq!(mirror[&9].value[0], 0.0);
        assert_eq!(mirror[&9].changed, 8);
        assert_eq!(mirror[&4].changed, 1);
        assert_eq!(mirror[&1_000_000].value[0], 5.0);
        assert!(refresh(&mut mirror, &problem, Some(&[]), 9).is_empty());
    }

    /// A landing refreshes in slices of at most `at_most` entries or values, resuming where
    /// the last stopped: on both paths it ends where one pass does, each value changed once.
    #[test]
    fn a_refresh_in_slices_ends_where_one_pass_does() {
        let keys: Vec<Key> = (0..64).map(|i| (i * 37) % 64 + 1).collect();
        // Every third variable (looked up, a few of many) or all but a few (walked), and the
        // mirror without one of them, so that a slice may end on a value it lacks.
        let few: Vec<usize> = (0..64).step_by(3).take(6).collect();
        let many: Vec<usize> = (0..60).collect();
        for moved in [&few[..], &many[..]] {
            let (problem, mut whole) = setup(&keys);
            whole.remove(&keys[10]);
            let mut sliced = whole.clone();
            let moved = MovedValues::encode(&problem, Some(moved));
            let walk = moved.walks(whole.len());
            let (all, done) = refresh_observed(
                &mut whole,
                moved.values(),
                walk,
                usize::MAX,
                7,
                &mut |_, _| {},
            );
            assert_eq!(done, moved.values().len());
            let (mut changed, mut done, mut slices) = (Vec::new(), 0, 0);
            while done < moved.values().len() {
                let (some, more) = refresh_observed(
                    &mut sliced,
                    &moved.values()[done..],
                    walk,
                    5,
                    7,
                    &mut |_, _| {},
                );
                assert!(more > 0, "a slice makes progress");
                changed.extend(some);
                done += more;
                slices += 1;
            }
            assert!(slices > 1, "the case is sliced");
            assert_eq!(refreshed(&changed), refreshed(&all), "walk: {walk}");
            assert_eq!(changed.len(), all.len(), "each value changed once");
            for (key, entry) in &whole {
                assert_eq!(sliced[key].value, entry.value, "key {key}");
                assert_eq!(sliced[key].changed, entry.changed, "key {key}");
            }
        }
    }
}
