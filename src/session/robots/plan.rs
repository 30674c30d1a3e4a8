//! What a batch does to the robots: its robots' new values moved into their component's frame,
//! its factors routed (into the problem, or held between components not merged), and the merges
//! its closures complete, decided from the mirror's estimate.

use std::collections::{BTreeMap, BTreeSet};
use std::time::Instant;

use super::consensus::{self, Candidate};
use super::{Component, Frame, Robot, Robots};
use crate::api::catalogue;
use crate::api::robots::{robot_of_key, MergeRecord, MergeReport};
use crate::api::wire::{FactorId, VariableValue, WireValue};
use crate::problem::{Key, Variable};
use crate::session::batch::{PreparedBatch, PreparedFactor};
use crate::session::mirror::value_of;
use crate::session::MirrorEntry;
use crate::solver::chi_square::cached_quantile;

/// A merge as the problem applies it (after the batch's own variables and factors).
pub(crate) struct Merge {
    /// Every key of the moved component, and the transform that moves it.
    pub moved_keys: Vec<Key>,
    pub frame: Frame,
    /// The closures that enter the problem with it.
    pub closures: Vec<(FactorId, PreparedFactor)>,
}

/// What routing a batch left for the problem and the journal.
#[derive(Default)]
pub(crate) struct RobotsPlan {
    /// The ids of the batch's factors that enter the problem now (in batch order).
    pub active_ids: Vec<FactorId>,
    pub merges: Vec<Merge>,
    /// The journal's record of each decision, and what its `merge` event says (none for
    /// closures admitted within one component).
    pub records: Vec<(MergeRecord, Option<MergeReport>)>,
    /// The values a merge moved, as the mirror now holds them (changed at the merge's
    /// sequence): the batch's `estimate` event carries them, so streams and `since` reads see
    /// the moved robots in the map without waiting for a solve to change them again.
    pub moved_values: Vec<VariableValue>,
}

/// The robot a variable belongs to: a pose (se2, se3) whose key names a robot.
pub(super) fn robot_of(key: Key, v: &dyn Variable) -> Option<u8> {
    matches!(v.kind(), "se2" | "se3")
        .then(|| robot_of_key(key))
        .flatten()
        .map(|c| c as u8)
}

impl Robots {
    /// Moves the batch's new robot poses given in their robot's odometry frame into its
    /// component's frame (predicted ones are there already), before the mirror takes them.
    pub(crate) fn place_new_values(&self, prepared: &mut PreparedBatch) {
        for v in &mut prepared.variables {
            if prepared.predicted.contains(&v.key) {
                continue;
            }
            if let Some(robot) = robot_of(v.key, v.value.as_ref()).and_then(|r| self.robots.get(&r))
            {
                robot.frame.apply(v.value.as_mut());
            }
        }
    }

    /// Routes the batch (its factors have `ids`): new variables join their robot's component
    /// or found one, factors join components or are held, and (unless `replay`: the journal's
    /// merge records follow) the closures that now agree merge components, moving the mirror's
    /// values. The held factors leave `prepared`.
    pub(crate) fn route(
        &mut self,
        prepared: &mut PreparedBatch,
        ids: &[FactorId],
        mirror: &mut BTreeMap<Key, MirrorEntry>,
        sequence: u64,
        replay: bool,
    ) -> RobotsPlan {
        for v in &prepared.variables {
            let Some(r) = robot_of(v.key, v.value.as_ref()) else {
                continue;
            };
            match self.robots.get_mut(&r) {
                Some(robot) => {
                    robot.poses += 1;
                    let first = robot.first;
                    self.union(first, v.key);
                }
                None => {
                    let frame = match v.value.kind() {
                        "se3" => Frame::Spatial(crate::geometry::Se3::identity()),
                        _ => Frame::Planar(crate::geometry::Se2::identity()),
                    };
                    self.robots.insert(
                        r,
                        Robot {
                            first: v.key,
                            poses: 1,
                            frame,
                        },
                    );
                    let founded = self.next_founding;
                    self.next_founding += 1;
                    self.components.insert(
                        self.find(v.key),
                        Component {
                            robots: BTreeSet::from([r]),
                            founded,
                        },
                    );
                }
            }
        }
        let mut plan = RobotsPlan::default();
        let mut touched: Vec<Vec<Key>> = Vec::new();
        let factors = std::mem::take(&mut prepared.factors);
        for (f, &id) in factors.into_iter().zip(ids) {
            let keys = f.factor.keys().to_vec();
            let placed = self.placed_roots(&keys);
            if placed.len() >= 2 {
                self.pending.insert(id, keys.clone());
                self.held.insert(id, f);
                touched.push(keys);
            } else {
                for w in keys.windows(2) {
                    self.union(w[0], w[1]);
                }
                prepared.factors.push(f);
                plan.active_ids.push(id);
            }
        }
        if !replay {
            let start = Instant::now();
            let mut merged = false;
            for keys in touched {
                let roots = self.placed_roots(&keys);
                if roots.len() == 2 {
                    if let Some(record) = self.decide(roots[0], roots[1], mirror) {
                        let seconds = start.elapsed().as_secs_f64();
                        merged |= self
                            .apply_record(record, sequence, seconds, mirror, &mut plan)
                            .is_some();
                    }
                }
            }
            self.batches_since_check += 1;
            if merged || self.batches_since_check >= RECHECK_EVERY {
                self.batches_since_check = 0;
                let closures = self.fitting(mirror);
                if !closures.is_empty() {
                    let record = MergeRecord {
                        closures,
                        rejected: Vec::new(),
                        transform: Vec::new(),
                    };
                    self.apply_record(record, sequence, 0.0, mirror, &mut plan);
                }
            }
        }
        plan
    }

    /// Of two components (roots) about to merge, the one that keeps its frame (the older) and
    /// the one that moves.
    fn kept_and_moved(&self, x: Key, y: Key) -> (Key, Key) {
        if self.components[&x].founded <= self.components[&y].founded {
            (x, y)
        } else {
            (y, x)
        }
    }

    /// The distinct roots of `keys` whose components hold robots, in key order.
    pub(super) fn placed_roots(&self, keys: &[Key]) -> Vec<Key> {
        let mut roots: Vec<Key> = Vec::new();
        for &k in keys {
            let r = self.find(k);
            if self.components.contains_key(&r) && !roots.contains(&r) {
                roots.push(r);
            }
        }
        roots
    }

    /// Whether the held closures between components `x` and `y` now agree enough to merge
    /// them: the record of the merge, found from the estimate in `mirror`.
    fn decide(&self, x: Key, y: Key, mirror: &BTreeMap<Key, MirrorEntry>) -> Option<MergeRecord> {
        let (kept, moved) = self.kept_and_moved(x, y);
        let between: Vec<FactorId> = self
            .pending
            .iter()
            .filter(|(_, keys)| {
                let r = self.placed_roots(keys);
                r.len() == 2 && r.contains(&kept) && r.contains(&moved)
            })
            .map(|(&id, _)| id)
            .collect();
        if between.len() < self.options.min_closures {
            return None;
        }
        let newest = &between[between.len().saturating_sub(consensus::MAX_CANDIDATES)..];
        let mut usable: Vec<(FactorId, Closure)> = Vec::new();
        for &id in newest {
            let keys = &self.pending[&id];
            if let Some(c) = Closure::new(&self.held[&id], keys, |k| self.find(k) == moved, mirror)
            {
                usable.push((id, c));
            }
        }
        let candidates: Vec<Candidate> = usable
            .iter()
            .map(|(_, c)| Candidate {
                implied: c.implied,
                dof: c.dof,
                ends: c.ends,
            })
            .collect();
        let mut chi2 = |k: usize, t: &Frame| usable[k].1.chi2_under(&self.held[&usable[k].0], t);
        let mut agree = |i: usize, j: usize| consensus::agree(&candidates, i, j, &mut chi2);
        let set = consensus::largest_consistent_set(candidates.len(), &mut agree);
        if set.len() < self.options.min_closures {
            return None;
        }
        let frames: Vec<Frame> = set.iter().map(|&i| candidates[i].implied).collect();
        let transform = Frame::mean(&frames)?;
        let closures: Vec<FactorId> = set.iter().map(|&i| usable[i].0).collect();
        let rejected = between
            .into_iter()
            .filter(|id| !closures.contains(id))
            .collect();
        Some(MergeRecord {
            closures,
            rejected,
            transform: transform.to_wire(),
        })
    }

    /// Carries out a journalled decision: a merge, or (an empty transform) the admission of
    /// held closures within one component. `None` when the record does not fit the state (a
    /// corrupt journal).
    pub(crate) fn apply_record(
        &mut self,
        record: MergeRecord,
        sequence: u64,
        seconds: f64,
        mirror: &mut BTreeMap<Key, MirrorEntry>,
        plan: &mut RobotsPlan,
    ) -> Option<()> {
        if !record.transform.is_empty() {
            return self.merge(record, sequence, seconds, mirror, plan);
        }
        let mut closures = Vec::new();
        for id in &record.closures {
            let keys = self.pending.get(id)?;
            if self.placed_roots(keys).len() != 1 {
                return None;
            }
            self.pending.remove(id);
            closures.push((*id, self.held.remove(id)?));
        }
        self.admitted += closures.len() as u64;
        plan.merges.push(Merge {
            moved_keys: Vec::new(),
            frame: Frame::Planar(crate::geometry::Se2::identity()),
            closures,
        });
        plan.records.push((record, None));
        Some(())
    }

    /// Carries out a merge: the moved component's values (mirror) and robots' frames move by
    /// the record's transform, its closures leave the held ones for the problem; the others
    /// between the two stay held, now within one component, re-checked against the map.
    fn merge(
        &mut self,
        record: MergeRecord,
        sequence: u64,
        seconds: f64,
        mirror: &mut BTreeMap<Key, MirrorEntry>,
        plan: &mut RobotsPlan,
    ) -> Option<()> {
        let frame = Frame::from_wire(&record.transform)?;
        let keys = self.pending.get(record.closures.first()?)?.clone();
        let roots = self.placed_roots(&keys);
        let [x, y] = roots[..] else { return None };
        let (kept, moved) = self.kept_and_moved(x, y);
        let names = |root: Key| -> Vec<String> {
            self.components[&root]
                .robots
                .iter()
                .map(|&r| (r as char).to_string())
                .collect()
        };
        let (kept_names, moved_names) = (names(kept), names(moved));
        let moved_keys = self.members(moved, mirror.keys().copied());
        for k in &moved_keys {
            if let Some(entry) = mirror.get_mut(k) {
                let mut v = entry.decode();
                if frame.apply(v.as_mut()) {
                    entry.value = WireValue::from_vec(catalogue::encode_variable(v.as_ref()));
                    entry.changed = sequence;
                    plan.moved_values.push(value_of(*k, entry));
                }
            }
        }
        for &r in &self.components[&moved].robots.clone() {
            let robot = self.robots.get_mut(&r).expect("a component's robots exist");
            robot.frame = frame.compose(&robot.frame).unwrap_or(robot.frame);
        }
        self.union(kept, moved);
        let mut closures = Vec::new();
        for id in &record.closures {
            self.pending.remove(id);
            if let Some(f) = self.held.remove(id) {
                closures.push((*id, f));
            }
        }
        let report = MergeReport {
            sequence,
            kept: kept_names,
            moved: moved_names,
            transform: record.transform.clone(),
            closures: record.closures.clone(),
            rejected: record.rejected.clone(),
            seconds,
        };
        self.merges.push(report.clone());
        plan.merges.push(Merge {
            moved_keys,
            frame,
            closures,
        });
        plan.records.push((record, Some(report)));
        Some(())
    }

    /// The held closures within one component (left over from a merge) that now fit the map:
    /// their error at the estimate is within [`ADMIT_GATE`] times the χ² quantile of their
    /// dimension at 99.9 %. A wrong closure's error stays thousands.
    fn fitting(&self, mirror: &BTreeMap<Key, MirrorEntry>) -> Vec<FactorId> {
        self.pending
            .iter()
            .filter(|(_, keys)| self.placed_roots(keys).len() == 1)
            .filter(|(id, keys)| {
                let f = &self.held[id];
                let gate = ADMIT_GATE * cached_quantile(f.factor.residual_dim(), 0.999);
                chi2_at(f, keys, mirror).is_some_and(|c| c <= gate)
            })
            .map(|(&id, _)| id)
            .collect()
    }
}

/// How far past the χ² quantile a held closure's error at the estimate may be to enter the map
/// after its components merged: the estimate it is measured at is the optimum without it, where
/// a right closure's error also carries the map's own uncertainty.
const ADMIT_GATE: f64 = 10.0;

/// Held closures are checked against the map every this many batches (and after a merge).
const RECHECK_EVERY: u64 = 16;

/// `f`'s whitened squared error at the mirror's values of `keys`.
fn chi2_at(f: &PreparedFactor, keys: &[Key], mirror: &BTreeMap<Key, MirrorEntry>) -> Option<f64> {
    let values: Vec<Box<dyn Variable>> = keys
        .iter()
        .map(|k| mirror.get(k).map(MirrorEntry::decode))
        .collect::<Option<_>>()?;
    let refs: Vec<&dyn Variable> = values.iter().map(|v| v.as_ref()).collect();
    chi2_of(f, &refs)
}

/// `f`'s whitened squared error at `values` (no kernel: what the closure itself says).
fn chi2_of(f: &PreparedFactor, values: &[&dyn Variable]) -> Option<f64> {
    let d = f.factor.residual_dim();
    let (mut e, mut w) = (vec![0.0; d], vec![0.0; d]);
    f.factor.evaluate(values, &mut e, None).ok()?;
    f.sqrt_information.whiten_vector(&e, &mut w);
    let s: f64 = w.iter().map(|x| x * x).sum();
    s.is_finite().then_some(s)
}

/// A held closure between the kept and the moved component, as the consensus evaluates it.
struct Closure {
    implied: Frame,
    dof: usize,
    ends: [Option<(u8, u64)>; 2],
    /// The closure's variables at the estimate; `moved` marks those of the moved component.
    values: Vec<Box<dyn Variable>>,
    moved: Vec<bool>,
}

impl Closure {
    /// `None` when the factor cannot say where its moved end lies from its kept end (only
    /// two-variable factors that predict a pose serve), or a value is missing.
    fn new(
        f: &PreparedFactor,
        keys: &[Key],
        in_moved: impl Fn(Key) -> bool,
        mirror: &BTreeMap<Key, MirrorEntry>,
    ) -> Option<Closure> {
        let [a, b] = keys[..] else { return None };
        let values: Vec<Box<dyn Variable>> = keys
            .iter()
            .map(|k| mirror.get(k).map(MirrorEntry::decode))
            .collect::<Option<_>>()?;
        let moved: Vec<bool> = keys.iter().map(|&k| in_moved(k)).collect();
        let (kept_at, moved_at) = match (moved[0], moved[1]) {
            (false, true) => (0, 1),
            (true, false) => (1, 0),
            _ => return None,
        };
        let mut known: Vec<Option<&dyn Variable>> =
            values.iter().map(|v| Some(v.as_ref())).collect();
        known[moved_at] = None;
        let predicted = f.factor.predict(&known, moved_at)?;
        let implied = Frame::between_poses(predicted.as_ref(), values[moved_at].as_ref())?;
        let end = |k: Key| robot_of_key(k).map(|c| (c as u8, k & ((1 << 56) - 1)));
        let mut ends = [end(a), end(b)];
        if kept_at == 1 {
            ends.swap(0, 1);
        }
        Some(Closure {
            implied,
            dof: f.factor.residual_dim(),
            ends,
            values,
            moved,
        })
    }

    /// The closure's whitened squared error with its moved end placed by `t`.
    fn chi2_under(&self, f: &PreparedFactor, t: &Frame) -> Option<f64> {
        let placed: Vec<Box<dyn Variable>> = self
            .values
            .iter()
            .zip(&self.moved)
            .map(|(v, &m)| {
                let mut v = v.clone_box();
                (!m || t.apply(v.as_mut())).then_some(v)
            })
            .collect::<Option<_>>()?;
        let refs: Vec<&dyn Variable> = placed.iter().map(|v| v.as_ref()).collect();
        chi2_of(f, &refs)
    }
}
