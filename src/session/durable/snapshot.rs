//! Snapshots written off the session lock.
//!
//! The session lock (with the journal's) is held only to take a [`Capture`]: the sequence, the
//! journal's length, and the changes journalled since the last capture, moved out of the
//! journal side in O(1). A blocking thread then brings the [`Base`] (the journalled variables
//! and factors as of the last capture, owned by whoever writes snapshots) up to date with those
//! changes, reads the estimate from the mirror in chunks of [`CHUNK`] variables (a short lock
//! each), serialises, writes `snapshot.json` and compacts the journal (see
//! [`crate::journal::Compaction`]): only records before the captured length are dropped, so
//! what was journalled meanwhile stays.
//!
//! One snapshot at a time: the base is taken out of the journal side for the write and put back
//! at its end, and no snapshot starts while it is out. Deletion: every write into the session's
//! directory happens holding [`Files`] with `alive` true; burying the directory takes that lock
//! and clears it, so a snapshot in flight either finished its write before the directory was
//! renamed or writes nothing (a session of the same name created after that is never touched).
//!
//! The estimate is read after the capture, a chunk at a time: a variable's value may come from
//! a solve after the snapshot's sequence. Replaying the journal's later records on it gives the
//! same problem (variables are never removed; fixes and guesses are replayed; fixed variables do
//! not move in solves), and the values are only where the recovery's solve starts from.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::super::Session;
use crate::api::wire::{AutoOptimize, FactorId, FactorSpec, VariableSpec};
use crate::journal::{Compaction, ProducerRecord, SessionDir, SnapshotOut};
use crate::problem::Key;

/// Variables read from the mirror per lock while a snapshot is written.
pub(super) const CHUNK: usize = 128;
/// Map node and allocation overhead, as the session's other estimates count it.
const NODE: usize = 48;

/// Whether the session's directory is still its own: writes into it hold this lock with `true`.
pub(super) type Files = Arc<Mutex<bool>>;

/// Something journalled that a snapshot must hold.
pub(super) enum Change {
    /// `given`: its value as the client gave it (wire encoding), kept for a bundle adjustment.
    Variable {
        key: Key,
        kind: &'static str,
        fixed: bool,
        given: Option<Vec<f64>>,
    },
    /// A bundle adjustment's guess: the variable's given value from now on.
    Given {
        key: Key,
        value: Vec<f64>,
    },
    Fix {
        key: Key,
        fixed: bool,
    },
    Factor {
        id: FactorId,
        spec: FactorSpec,
    },
    Remove {
        id: FactorId,
    },
}

impl Change {
    /// Estimated bytes it holds.
    pub(super) fn bytes(&self) -> usize {
        match self {
            Change::Factor { spec, .. } => spec_bytes(spec),
            Change::Variable {
                given: Some(value), ..
            }
            | Change::Given { value, .. } => std::mem::size_of::<Change>() + 8 * value.len(),
            _ => std::mem::size_of::<Change>(),
        }
    }
}

/// Estimated bytes of a factor's wire form.
pub(super) fn spec_bytes(f: &FactorSpec) -> usize {
    std::mem::size_of::<FactorSpec>()
        + NODE
        + 8 * (f.keys.len()
            + f.measurement.len()
            + f.information.as_ref().map_or(0, Vec::len)
            + f.sigmas.as_ref().map_or(0, Vec::len))
        + f.factor_type.len()
}

const VARIABLE_BYTES: usize = std::mem::size_of::<(Key, VariableMeta)>() + NODE;

#[derive(Clone, Debug, PartialEq)]
struct VariableMeta {
    kind: &'static str,
    fixed: bool,
    /// A bundle adjustment's given value (see [`Change::Variable`]).
    given: Option<Vec<f64>>,
}

impl VariableMeta {
    fn bytes(&self) -> usize {
        VARIABLE_BYTES + self.given.as_ref().map_or(0, |g| 8 * g.len())
    }
}

/// The journalled variables (kind, fixed, a bundle adjustment's given value) and factors (wire
/// form, by id) as of the last capture.
#[derive(Default)]
pub(super) struct Base {
    variables: BTreeMap<Key, VariableMeta>,
    factors: BTreeMap<FactorId, FactorSpec>,
    /// Estimated bytes held, kept as changes are applied.
    bytes: usize,
}

impl Base {
    pub(super) fn bytes(&self) -> usize {
        self.bytes
    }

    /// Applies changes in the order they were journalled.
    pub(super) fn apply(&mut self, changes: Vec<Change>) {
        for change in changes {
            match change {
                Change::Variable {
                    key,
                    kind,
                    fixed,
                    given,
                } => {
                    let meta = VariableMeta { kind, fixed, given };
                    self.bytes += meta.bytes();
                    if let Some(old) = self.variables.insert(key, meta) {
                        self.bytes -= old.bytes();
                    }
                }
                Change::Given { key, value } => {
                    if let Some(meta) = self.variables.get_mut(&key) {
                        self.bytes -= meta.bytes();
                        meta.given = Some(value);
                        self.bytes += meta.bytes();
                    }
                }
                Change::Fix { key, fixed } => {
                    if let Some(meta) = self.variables.get_mut(&key) {
                        meta.fixed = fixed;
                    }
                }
                Change::Factor { id, spec } => {
                    self.bytes += spec_bytes(&spec);
                    if let Some(old) = self.factors.insert(id, spec) {
                        self.bytes -= spec_bytes(&old);
                    }
                }
                Change::Remove { id } => {
                    if let Some(old) = self.factors.remove(&id) {
                        self.bytes -= spec_bytes(&old);
                    }
                }
            }
        }
    }

    /// The estimate from walking everything (what `bytes` keeps): for tests.
    #[cfg(test)]
    pub(super) fn walked_bytes(&self) -> usize {
        self.variables
            .values()
            .map(VariableMeta::bytes)
            .sum::<usize>()
            + self.factors.values().map(spec_bytes).sum::<usize>()
    }
}

/// What a snapshot takes under the session lock: O(1) (the changes and the base move).
pub(super) struct Capture {
    pub(super) sequence: u64,
    pub(super) next_factor_id: FactorId,
    pub(super) auto: AutoOptimize,
    /// Every producer's progress at `sequence`.
    pub(super) producers: Vec<ProducerRecord>,
    /// Every factor type declared at `sequence`.
    pub(super) factor_types: Vec<crate::factors::expression::FactorTypeDefinition>,
    /// The journal's length: the records the snapshot makes redundant.
    pub(super) journal_bytes: u64,
    pub(super) journal_path: PathBuf,
    pub(super) changes: Vec<Change>,
    pub(super) base: Box<Base>,
    pub(super) dir: SessionDir,
    pub(super) files: Files,
    /// When the capture began.
    pub(super) started: Instant,
}

/// How a snapshot ended.
enum Outcome {
    /// `compaction`: the journal's records after the snapshot, copied as far as they were.
    Written {
        bytes: usize,
        compaction: Compaction,
    },
    /// The session was deleted meanwhile: nothing was written.
    Abandoned,
}

impl Session {
    /// Writes the snapshot `capture` was taken for (on a blocking thread), then gives the base
    /// back to the journal side so the next one may start.
    pub(super) fn write_snapshot(self: &Arc<Self>, capture: Capture) {
        let Capture {
            sequence,
            next_factor_id,
            auto,
            producers,
            factor_types,
            journal_bytes,
            journal_path,
            changes,
            mut base,
            dir,
            files,
            started,
        } = capture;
        let pending_bytes: usize = changes.iter().map(Change::bytes).sum();
        base.apply(changes);
        let mut chunk_locked = Duration::ZERO;
        let outcome = self
            .snapshot_variables(&base)
            .and_then(|(variables, longest)| {
                chunk_locked = longest;
                let given: Vec<(Key, &[f64])> = base
                    .variables
                    .iter()
                    .filter_map(|(&key, meta)| Some((key, meta.given.as_deref()?)))
                    .collect();
                let bytes = serde_json::to_vec(&SnapshotOut {
                    sequence,
                    next_factor_id,
                    auto_optimize: auto,
                    variables: &variables,
                    factors: &base.factors,
                    producers: &producers,
                    factor_types: &factor_types,
                    given: &given,
                })
                .expect("snapshots serialise");
                drop(variables);
                self.persist(&dir, &files, &bytes, journal_bytes, &journal_path)
            });
        let mut durable = self.durable.lock().unwrap_or_else(|p| p.into_inner());
        let Some(d) = durable.as_mut() else {
            return; // buried meanwhile
        };
        let compacted = match outcome {
            Ok(Outcome::Written { bytes, compaction }) => {
                d.last_snapshot_bytes = bytes;
                let locked = Instant::now();
                let compacted = compaction.finish(&mut d.journal);
                // `finish_locked_ms`: the journal's lock held for the records appended meanwhile
                // (appends wait for it; the session's lock is not held);
                // `longest_session_lock_us`: the longest hold of the session's lock for a chunk
                // of the estimate.
                tracing::info!(
                    session = self.name,
                    sequence,
                    bytes,
                    seconds = started.elapsed().as_secs_f64(),
                    finish_locked_ms = locked.elapsed().as_secs_f64() * 1e3,
                    longest_session_lock_us = chunk_locked.as_secs_f64() * 1e6,
                    "snapshot written"
                );
                compacted.map_err(|e| format!("compacting the journal failed: {e}"))
            }
            Ok(Outcome::Abandoned) => Ok(()),
            Err(e) => Err(e),
        };
        if let Err(e) = compacted {
            tracing::warn!(
                session = self.name,
                sequence,
                "snapshot failed (the journal keeps everything): {e}"
            );
        }
        d.give_back(base, pending_bytes);
    }

    /// Every variable of `base` with its current value, read from the mirror a chunk at a time.
    /// Also returns the longest the session's lock was held for a chunk.
    fn snapshot_variables(&self, base: &Base) -> Result<(Vec<VariableSpec>, Duration), String> {
        let mut out = Vec::with_capacity(base.variables.len());
        let mut longest = Duration::ZERO;
        let mut variables = base.variables.iter().peekable();
        while variables.peek().is_some() {
            let st = self.lock();
            let locked = Instant::now();
            for (&key, meta) in variables.by_ref().take(CHUNK) {
                let entry =
                    st.mirror.entries.get(&key).ok_or_else(|| {
                        format!("variable {key} is journalled but not in the mirror")
                    })?;
                out.push(VariableSpec {
                    key,
                    kind: meta.kind.into(),
                    value: Some(entry.value.to_vec()),
                    fixed: meta.fixed,
                    stamp: entry.stamp,
                });
            }
            longest = longest.max(locked.elapsed());
            drop(st);
        }
        Ok((out, longest))
    }

    /// Writes the snapshot and copies the journal's records after it, holding `files`.
    fn persist(
        &self,
        dir: &SessionDir,
        files: &Files,
        bytes: &[u8],
        journal_bytes: u64,
        journal_path: &std::path::Path,
    ) -> Result<Outcome, String> {
        let alive = files.lock().unwrap_or_else(|p| p.into_inner());
        if !*alive {
            return Ok(Outcome::Abandoned);
        }
        dir.write_snapshot(bytes).map_err(|e| e.to_string())?;
        let mut compaction = Compaction::new(journal_bytes);
        // Twice: the second pass takes what was appended during the first (its sync included),
        // leaving the fewest records for the pass under the journal's lock.
        for _ in 0..2 {
            let upto = self
                .durable
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .as_ref()
                .map(|d| d.journal.bytes());
            if let Some(upto) = upto {
                compaction
                    .copy_until(journal_path, upto)
                    .map_err(|e| format!("copying the journal's tail failed: {e}"))?;
            }
        }
        Ok(Outcome::Written {
            bytes: bytes.len(),
            compaction,
        })
    }
}
