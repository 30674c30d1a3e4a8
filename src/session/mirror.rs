//! The mirror: every accepted variable as clients see it (kind, wire value, when it changed),
//! kept apart from the problem so reads never wait for a solve that has the problem.

use super::engine::Engine;
use super::Session;
use crate::api::catalogue;
use crate::api::export::{self, EstimateFormat, Export};
use crate::api::wire::{Estimate, EstimateQuery, VariableValue};
use crate::api::ServiceError;
use crate::problem::{Key, Variable};

/// A variable's wire value, inline up to an SE(3) pose's 7 numbers. After a loop closure a
/// solve compares and rewrites hundreds of these under the session lock; with each value in
/// an allocation of its own, every one cost a second cache miss (M3500 over HTTP: 6.6% of the
/// server's samples in that loop, most of them on the value's first load).
pub type WireValue = smallvec::SmallVec<[f64; 7]>;

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
                (self.lock().sequence, variables)
            }
            Engine::Graph(_) => {
                let st = self.lock();
                let since = query.since.unwrap_or(0);
                let variables = if range.start() > range.end() {
                    Vec::new()
                } else {
                    st.mirror
                        .range(range)
                        .filter(|(_, e)| query.since.is_none() || e.changed > since)
                        .map(|(&k, e)| value_of(k, e))
                        .collect()
                };
                (st.sequence, variables)
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
        value: e.value.to_vec(),
        changed: e.changed,
        stamp: e.stamp,
    }
}
