//! A session rebuilt at start from what its directory held (its snapshot, then the journal
//! entries after it), and the read-only state a session falls into when its files cannot be
//! recovered whole.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Instant;

use super::super::engine::Engine;
use super::super::Session;
use super::Durability;
use crate::api::fusion::FusionBatch;
use crate::api::wire::{AutoOptimize, Batch, FactorId, FactorSpec};
use crate::journal::{Entry, Recovered, Snapshot};

/// How a session came back at start.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Recovery {
    pub snapshot_sequence: Option<u64>,
    pub entries: usize,
    pub truncated_bytes: u64,
    pub seconds: f64,
    /// The journal was damaged (a bad record that is not a torn tail): the session holds the
    /// entries before the damage and is read-only (see [`Session::corruption`]).
    pub corruption: Option<String>,
}

impl Session {
    pub fn is_recovering(&self) -> bool {
        self.recovering.load(Ordering::SeqCst)
    }

    pub fn mark_recovering(&self) {
        self.recovering.store(true, Ordering::SeqCst);
    }

    /// A recovery that stopped part way (a damaged snapshot, an entry that does not replay):
    /// the session keeps what was rebuilt and becomes read-only for good, so writes cannot
    /// extend a journal that no longer replays; its statistics say why. DELETE still works.
    pub fn recovery_failed(&self, reason: &str) {
        self.mark_corrupt(format!(
            "recovery stopped: {reason}; the session keeps what was rebuilt and is read-only \
             (its files are kept unchanged; DELETE removes them)"
        ));
    }

    /// Makes the session read-only for good, with `reason` as its `last_error`. Set before
    /// `recovering` clears (when it is recovering), so no write slips in between.
    pub(super) fn mark_corrupt(&self, reason: String) {
        let _ = self.corruption.set(reason);
        self.recovering.store(false, Ordering::SeqCst);
    }

    /// Why the session is read-only, when it is: its files could not be recovered whole, or its
    /// journal could not be made durable. It then refuses writes (409 `session_corrupt`).
    pub fn corruption(&self) -> Option<&String> {
        self.corruption.get()
    }

    /// Rebuilds the session from what its directory held: the snapshot, then every journal
    /// entry after it, with solves held back until the end; then optimises once. Blocking.
    /// `auto`: the policy it was created with.
    pub fn recover(
        self: &Arc<Self>,
        auto: AutoOptimize,
        recovered: Recovered,
        durability: Durability,
    ) -> Result<Recovery, String> {
        let start = Instant::now();
        let mut auto = auto;
        self.lock().auto = AutoOptimize::Manual {};
        self.attach(durability);
        let snapshot_sequence = recovered.snapshot.as_ref().map(|s| s.sequence);
        let snapshot_bytes = recovered.snapshot_bytes;
        let corruption = recovered.corruption;
        if let Some(snapshot) = recovered.snapshot {
            auto = self.restore_snapshot(snapshot)?;
        }
        let entries = recovered.entries.len();
        for (i, entry) in recovered.entries.into_iter().enumerate() {
            self.replay_entry(i, entry, snapshot_sequence.unwrap_or(0), &mut auto)?;
        }
        let dir = self
            .durable
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .as_mut()
            .map(|d| {
                d.entries_since_snapshot = entries as u64;
                // The next snapshot weighs the journal against the one recovered from.
                d.last_snapshot_bytes = snapshot_bytes;
                d.dir.clone()
            });
        if let Some(dir) = dir {
            self.restore_history(&dir);
        }
        let sequence = {
            let mut st = self.lock();
            st.auto = auto;
            st.mirror.sequence
        };
        match &corruption {
            Some(reason) => self.mark_corrupt(format!(
                "journal damaged: {reason}; the session holds what precedes the damage (up to \
                 sequence {sequence}) and is read-only (its files are kept unchanged; DELETE \
                 removes them)"
            )),
            None => self.recovering.store(false, Ordering::SeqCst),
        }
        // A window was optimised at every keyframe as its messages were replayed.
        if matches!(self.engine, Engine::Graph(_)) && sequence > 0 {
            self.optimize_now().map_err(|e| e.body.message)?;
        }
        Ok(Recovery {
            snapshot_sequence,
            entries,
            truncated_bytes: recovered.truncated_bytes,
            seconds: start.elapsed().as_secs_f64(),
            corruption,
        })
    }

    /// Restores a snapshot: its factor types, variables and factors (with their ids), its
    /// producers and sequence; returns the policy it holds.
    fn restore_snapshot(self: &Arc<Self>, snapshot: Snapshot) -> Result<AutoOptimize, String> {
        self.restore_factor_types(snapshot.factor_types)
            .map_err(|e| format!("snapshot: {e}"))?;
        let (ids, factors): (Vec<FactorId>, Vec<FactorSpec>) = snapshot.factors.into_iter().unzip();
        let batch = Batch {
            variables: snapshot.variables,
            factors,
            ..Batch::default()
        };
        self.replay_batch(batch, Some(ids), true)
            .map_err(|e| format!("snapshot: {}", e.body.message))?;
        self.restore_given(snapshot.given)?;
        let mut st = self.lock();
        st.producers = super::super::producers::Producers::from_records(snapshot.producers);
        st.mirror.sequence = snapshot.sequence;
        st.mirror.next_factor_id = st.mirror.next_factor_id.max(snapshot.next_factor_id);
        Ok(snapshot.auto_optimize)
    }

    /// Replays journal entry `i` (a batch already in the snapshot of `snapshot_sequence` is
    /// skipped, with its merges); a policy change goes to `auto`.
    fn replay_entry(
        self: &Arc<Self>,
        i: usize,
        entry: Entry,
        snapshot_sequence: u64,
        auto: &mut AutoOptimize,
    ) -> Result<(), String> {
        match entry {
            Entry::Batch { sequence, batch } => {
                let current = self.lock().mirror.sequence;
                if sequence <= current {
                    return Ok(()); // already in the snapshot
                }
                if sequence != current + 1 {
                    return Err(format!(
                        "journal entry {i} has sequence {sequence}, expected {}",
                        current + 1
                    ));
                }
                self.replay_batch(batch, None, false)
                    .map_err(|e| format!("journal entry {i}: {}", e.body.message))
            }
            Entry::Merge { sequence, merge } => {
                if sequence <= snapshot_sequence {
                    return Ok(()); // its batch is in the snapshot, and so is the merge
                }
                self.replay_merge(sequence, merge)
                    .map_err(|e| format!("journal entry {i}: {e}"))
            }
            Entry::AutoOptimize { auto_optimize } => {
                *auto = auto_optimize;
                Ok(())
            }
            Entry::FactorTypes { factor_types } => self
                .restore_factor_types(factor_types)
                .map_err(|e| format!("journal entry {i}: {e}")),
            Entry::Fusion { messages } => {
                let mut applied = 0;
                let mut window = self
                    .locked_window()
                    .map_err(|e| format!("journal entry {i}: {}", e.body.message))?;
                let batch = FusionBatch { messages };
                match self.apply_fusion_counted(&mut window, batch, &mut applied) {
                    Ok(_) => Ok(()),
                    // The window's solve failed here when the messages first came too; they
                    // were journalled because they stayed applied, and replay keeps them.
                    Err(e) if e.body.code == "solve_failed" => {
                        tracing::warn!(
                            session = self.name,
                            "journal entry {i}: {}",
                            e.body.message
                        );
                        Ok(())
                    }
                    Err(e) => Err(format!("journal entry {i}: {}", e.body.message)),
                }
            }
        }
    }
}
