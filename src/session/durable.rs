//! A session on disk: its journal entries are written under the session lock (so in sequence
//! order), and a batch is durable before it is acknowledged or anything reflecting it is
//! published (its fsync runs after the session lock is released, with the journal held: see
//! `apply.rs`). Snapshots compact the journal, and a session is rebuilt at start from its
//! snapshot plus the entries after it (`recovery.rs`; see `crate::journal`). Snapshots are
//! written off the session lock: `snapshot.rs`; the operators' history of the stream is kept
//! beside them: `history_file.rs`.

mod commit;
mod history_file;
mod recovery;
mod snapshot;

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::batch::PreparedBatch;
use super::{Session, State};
use crate::api::catalogue;
use crate::api::fusion::FusionBatch;
use crate::api::wire::{AutoOptimize, Batch, FactorId, FactorSpec};
use crate::api::ServiceError;
use crate::journal::{Entry, JournalConfig, JournalError, LogWriter, SessionDir};
use crate::problem::Key;
pub use recovery::Recovery;
use snapshot::{Base, Capture, Change, Files};

/// What makes a session durable: its directory, its open journal and the policy.
pub struct Durability {
    pub dir: SessionDir,
    pub journal: LogWriter,
    pub config: JournalConfig,
}

pub(super) struct Durable {
    dir: SessionDir,
    journal: LogWriter,
    config: JournalConfig,
    /// What was journalled since the last snapshot's capture, for the next one.
    changes: Vec<Change>,
    changes_bytes: usize,
    /// The variables and factors as of the last capture; out (`None`) while a snapshot is being
    /// written, which is what keeps snapshots one at a time.
    base: Option<Box<Base>>,
    /// Estimated bytes of the base, and of the changes a snapshot in flight is applying to it.
    base_bytes: usize,
    in_flight_bytes: usize,
    files: Files,
    entries_since_snapshot: u64,
    /// Bytes of the last snapshot written or recovered from (0: none), against which the
    /// journal's growth is weighed ([`PROPORTIONAL_SNAPSHOTS_FROM`]).
    last_snapshot_bytes: usize,
    /// Time the last append spent in fsync.
    pub(super) last_fsync: Duration,
}

fn journal_failed(name: &str, e: impl std::fmt::Display) -> ServiceError {
    // The update was not made durable, so it is not acknowledged (nor applied, unless only its
    // fsync failed: see `Session::journal_sync_failed`).
    ServiceError::unavailable(
        "journal_failed",
        format!("session `{name}`: the update could not be written to its journal: {e}"),
        5,
    )
}

/// From this size on, a session's next snapshot also waits for its journal to grow to
/// `journal.snapshot_journal_share` of the last one (0.25 by default). With a snapshot every
/// `snapshot_every` entries whatever its size, a 100 000-pose session wrote its 40 MB estimate
/// every 2 000 updates (about 20 MB/s of a stream at 1 ms an update, 50 times what the journal
/// itself wrote), and the journal's fsyncs waited behind those writes: a third to a half of
/// the answers over 3 ms of a budgeted stream at 90 000–100 000 poses came in the 400 updates
/// after a snapshot began (a fifth of the updates). Weighed against the journal, snapshots
/// write at most about 1 / share times the journal's bytes, and a recovery replays about that
/// share of the snapshot it loads at most.
const PROPORTIONAL_SNAPSHOTS_FROM: usize = 1 << 20;

impl Durable {
    /// Journals `entry`, durable (under `fsync always`) when this returns.
    pub(super) fn append(&mut self, name: &str, entry: &Entry) -> Result<(), ServiceError> {
        self.write(name, entry)?;
        self.sync(name)
    }

    fn write(&mut self, name: &str, entry: &Entry) -> Result<(), ServiceError> {
        let bytes = serde_json::to_vec(entry).expect("journal entries serialise");
        self.journal
            .write(&bytes)
            .map_err(|e| journal_failed(name, e))?;
        self.entries_since_snapshot += 1;
        Ok(())
    }

    /// Makes every entry written so far durable (under `fsync always`), then checks that this
    /// instance still owns the session (the fence, see `journal::takeover`): nothing written
    /// after another instance took it over may be acknowledged.
    pub(super) fn sync(&mut self, name: &str) -> Result<(), ServiceError> {
        self.last_fsync = self.journal.sync().map_err(|e| journal_failed(name, e))?;
        crate::runtime::metrics::observe_fsync(self.last_fsync);
        if self.dir.superseded() {
            return Err(super::ownership_lost(name));
        }
        Ok(())
    }

    /// Fills in the values the server predicted for variables sent without one (so a replay
    /// does not depend on the estimate it meets), then writes `batch` as `sequence` to the
    /// journal, not yet durable: the caller [`Self::sync`]s before acknowledging it (after
    /// releasing the session's lock, see `apply.rs`).
    pub(super) fn write_batch(
        &mut self,
        name: &str,
        sequence: u64,
        batch: Batch,
        prepared: &PreparedBatch,
        robots: Option<&super::robots::Robots>,
    ) -> Result<Batch, ServiceError> {
        let mut batch = batch;
        // `prepare` keeps the batch's variables in order, each with its value.
        for (spec, new) in batch.variables.iter_mut().zip(&prepared.variables) {
            debug_assert_eq!(spec.key, new.key);
            if spec.value.is_none() {
                // A predicted robot pose is in the map; the journal keeps a robot's values in
                // its odometry frame, as it sends them (a replay moves them into the map).
                let value = match robots {
                    Some(r) => r.in_odometry_frame(new.key, new.value.as_ref()),
                    None => new.value.clone_box(),
                };
                spec.value = Some(catalogue::encode_variable(value.as_ref()));
            }
        }
        let entry = Entry::Batch { sequence, batch };
        self.write(name, &entry)?;
        let Entry::Batch { batch, .. } = entry else {
            unreachable!("built above")
        };
        Ok(batch)
    }

    /// Writes the record of a merge batch `sequence` completed, right after the batch (not yet
    /// durable: the batch's fsync covers both).
    pub(super) fn write_merge(
        &mut self,
        name: &str,
        sequence: u64,
        merge: crate::api::robots::MergeRecord,
    ) -> Result<(), ServiceError> {
        self.write(name, &Entry::Merge { sequence, merge })
    }

    /// Records what a snapshot must hold of an accepted batch: its variables (kind, fixed), its
    /// fixes, its factors under their ids and its removals, in the order they are applied; with
    /// `keeps_given` (a bundle adjustment) also the values its client gave (the variables' and
    /// the guesses), which its restarts start from.
    pub(super) fn track(
        &mut self,
        specs: Vec<FactorSpec>,
        ids: &[FactorId],
        prepared: &PreparedBatch,
        keeps_given: bool,
    ) {
        let variables = prepared.variables.iter().map(|v| Change::Variable {
            key: v.key,
            kind: v.value.kind(),
            fixed: v.fixed,
            given: keeps_given.then(|| catalogue::encode_variable(v.value.as_ref())),
        });
        let fixes = prepared
            .fix
            .iter()
            .map(|&(key, fixed)| Change::Fix { key, fixed });
        let factors = ids
            .iter()
            .zip(specs)
            .map(|(&id, spec)| Change::Factor { id, spec });
        let removals = prepared.remove.iter().map(|&id| Change::Remove { id });
        let guesses = prepared
            .guesses
            .iter()
            .filter(|_| keeps_given)
            .map(|(key, value)| Change::Given {
                key: *key,
                value: catalogue::encode_variable(value.as_ref()),
            });
        let changes = variables.chain(fixes).chain(factors).chain(removals);
        for change in changes.chain(guesses) {
            self.push_change(change);
        }
    }

    /// Records a given value a snapshot restored (see [`Self::track`]).
    pub(super) fn track_given(&mut self, key: Key, value: Vec<f64>) {
        self.push_change(Change::Given { key, value });
    }

    fn push_change(&mut self, change: Change) {
        self.changes_bytes += change.bytes();
        self.changes.push(change);
    }

    /// Starts a snapshot once enough entries have accumulated and none is being written: takes
    /// what it needs in O(1) and writes it on a blocking thread (see `snapshot.rs`). A failure
    /// there leaves the journal (which holds everything) in place and is only logged; the next
    /// snapshot is tried `snapshot_every` entries later.
    ///
    /// Only graph sessions snapshot (batches are their only entries besides the policy): a
    /// window's state is more than variables and factors (its pre-integration, marginalisation
    /// priors), so it is rebuilt by replaying its messages. Nor do sessions with robots yet:
    /// a merge moves values the journal replays, and a snapshot reads the estimate after its
    /// capture, so a merge meanwhile would be applied twice; their journal keeps everything.
    pub(super) fn maybe_snapshot(&mut self, session: &Arc<Session>, st: &State) {
        if self.entries_since_snapshot < self.config.snapshot_every
            || st.robots.is_some()
            || self.journal_small_beside_snapshot()
        {
            return;
        }
        let Some(base) = self.base.take() else {
            return; // one is being written
        };
        let started = Instant::now();
        let capture = Capture {
            sequence: st.mirror.sequence,
            next_factor_id: st.mirror.next_factor_id,
            auto: st.auto,
            producers: st.producers.records(),
            factor_types: session.factor_types().definitions(),
            journal_bytes: self.journal.bytes(),
            journal_path: self.journal.path().to_path_buf(),
            changes: std::mem::take(&mut self.changes),
            base,
            dir: self.dir.clone(),
            files: Arc::clone(&self.files),
            started,
        };
        self.in_flight_bytes = std::mem::take(&mut self.changes_bytes);
        self.entries_since_snapshot = 0;
        tracing::debug!(
            session = session.name,
            sequence = st.mirror.sequence,
            micros = started.elapsed().as_secs_f64() * 1e6,
            "snapshot captured under the lock"
        );
        let session = Arc::clone(session);
        session
            .runtime
            .clone()
            .spawn_blocking(move || session.write_snapshot(capture));
    }

    /// Whether the journal since the last snapshot is still small beside it (see
    /// [`PROPORTIONAL_SNAPSHOTS_FROM`]).
    fn journal_small_beside_snapshot(&self) -> bool {
        self.last_snapshot_bytes >= PROPORTIONAL_SNAPSHOTS_FROM
            && (self.journal.bytes() as f64)
                < self.config.snapshot_journal_share * self.last_snapshot_bytes as f64
    }

    /// The base back from a snapshot (written or not): the next one may start.
    fn give_back(&mut self, base: Box<Base>, applied_bytes: usize) {
        debug_assert_eq!(applied_bytes, self.in_flight_bytes);
        self.base_bytes = base.bytes();
        self.in_flight_bytes = 0;
        self.base = Some(base);
    }

    /// Bytes this keeps in memory (the factors' wire form, the variables' kinds), in O(1).
    pub(super) fn memory_bytes(&self) -> usize {
        self.base_bytes + self.in_flight_bytes + self.changes_bytes
    }

    /// [`Durable::memory_bytes`] and the same estimate from walking what it counts; `None`
    /// while a snapshot has the base.
    #[cfg(test)]
    pub(super) fn bytes_kept_and_walked(&self) -> Option<(usize, usize)> {
        let base = self.base.as_ref()?;
        let walked = base.walked_bytes() + self.changes.iter().map(Change::bytes).sum::<usize>();
        Some((self.memory_bytes(), walked))
    }
}

impl Session {
    /// Makes the session durable from now on (its directory and journal exist).
    pub fn attach(&self, durability: Durability) {
        *self.durable.lock().unwrap_or_else(|p| p.into_inner()) = Some(Durable {
            dir: durability.dir,
            journal: durability.journal,
            config: durability.config,
            changes: Vec::new(),
            changes_bytes: 0,
            base: Some(Box::default()),
            base_bytes: 0,
            in_flight_bytes: 0,
            files: Arc::new(Mutex::new(true)),
            entries_since_snapshot: 0,
            last_snapshot_bytes: 0,
            last_fsync: Duration::ZERO,
        });
    }

    /// The session's sequence is `u64::MAX` (only damaged or edited files lead there: see
    /// `journal::snapshot_file`): it becomes read-only for good rather than give the next batch
    /// sequence 0 and reuse acknowledged sequences.
    pub(super) fn sequences_exhausted(&self) -> ServiceError {
        let reason = format!(
            "its sequence is {}, the last there is: another batch would wrap to sequence 0 and \
             reuse acknowledged sequences; the session is read-only (DELETE removes it)",
            u64::MAX
        );
        tracing::error!(session = self.name, "{reason}");
        self.mark_corrupt(reason.clone());
        ServiceError::conflict(
            "session_corrupt",
            format!("session `{}` is read-only: {reason}", self.name),
        )
    }

    /// Journals a policy change (durable sessions).
    pub(super) fn journal_auto_optimize(&self, auto: AutoOptimize) -> Result<(), ServiceError> {
        let mut durable = self.durable.lock().unwrap_or_else(|p| p.into_inner());
        match durable.as_mut() {
            Some(d) => d.append(
                &self.name,
                &Entry::AutoOptimize {
                    auto_optimize: auto,
                },
            ),
            None => Ok(()),
        }
    }

    /// Validates and applies fusion messages, journalling the ones the window accepted (all of
    /// them, or those before a rejected one) before answering. The window stays locked until
    /// they are journalled, so the journal holds concurrent batches in the order they were
    /// applied.
    pub fn apply_fusion(
        &self,
        batch: FusionBatch,
    ) -> Result<crate::api::fusion::FusionAck, ServiceError> {
        let mut window = self.locked_window()?;
        let copy = self
            .durable
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .is_some()
            .then(|| batch.messages.clone());
        let mut applied = 0;
        let result = self.apply_fusion_counted(&mut window, batch, &mut applied);
        if let Some(mut messages) = copy {
            messages.truncate(applied);
            if !messages.is_empty() {
                let mut durable = self.durable.lock().unwrap_or_else(|p| p.into_inner());
                match durable.as_mut() {
                    Some(d) => d.append(&self.name, &Entry::Fusion { messages })?,
                    // Its files were closed meanwhile (deleted, or handed to another instance
                    // of a fleet): what was applied here is dropped with it, so it must not be
                    // acknowledged.
                    None => return Err(self.gone()),
                }
            }
        }
        result
    }

    /// A batch was applied but its journal entry could not be made durable: whether it reached
    /// the disk is unknown (a failed fsync may have dropped the written pages), so the session
    /// stops taking writes rather than go on from a state its files may not hold. A restart
    /// recovers it from what the journal does hold.
    pub(super) fn journal_sync_failed(&self, error: ServiceError) -> ServiceError {
        let reason = format!(
            "its journal could not be made durable ({}); restart the server to recover the \
             session from its files",
            error.body.message
        );
        tracing::error!(session = self.name, "{reason}");
        self.mark_corrupt(reason);
        error
    }

    /// Under `fsync: interval`: makes what was appended so far durable.
    pub fn sync_journal(&self) {
        let handle = self
            .durable
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .as_ref()
            .map(|d| d.journal.handle());
        if let Some(file) = handle {
            let start = Instant::now();
            if let Err(e) = file.sync_data() {
                tracing::warn!(session = self.name, "journal fsync failed: {e}");
            }
            crate::runtime::metrics::observe_fsync(start.elapsed());
        }
    }

    /// Deletes the session's files through `bury` (which makes the deletion durable, see
    /// [`SessionDir::bury`]) with the journal held, so no append runs meanwhile; closes the
    /// journal once they are buried. On failure nothing changed and the session stays durable.
    pub fn bury_files<T>(
        &self,
        bury: impl FnOnce() -> Result<T, JournalError>,
    ) -> Result<T, JournalError> {
        // A snapshot writing into the directory finishes first; none writes there afterwards.
        let files = self
            .durable
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .as_ref()
            .map(|d| Arc::clone(&d.files));
        let mut alive = files
            .as_ref()
            .map(|f| f.lock().unwrap_or_else(|p| p.into_inner()));
        let mut durable = self.durable.lock().unwrap_or_else(|p| p.into_inner());
        // Another instance took the session over: its directory is that one's now.
        if let Some(dir) = durable.as_ref().map(|d| &d.dir).filter(|d| d.superseded()) {
            return Err(JournalError::Superseded {
                path: dir.path().to_path_buf(),
            });
        }
        let buried = bury()?;
        durable.take();
        if let Some(alive) = alive.as_mut() {
            **alive = false;
        }
        Ok(buried)
    }

    pub(super) fn durable_memory_bytes(&self) -> usize {
        self.durable
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .as_ref()
            .map_or(0, Durable::memory_bytes)
    }
}
