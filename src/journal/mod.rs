//! Durable sessions: every accepted update is appended to the session's write-ahead journal
//! before it is acknowledged; snapshots of the estimate and the problem compact the journal; on
//! start every session is rebuilt from its snapshot plus the journal written after it.
//!
//! Layout under the state directory:
//!
//! ```text
//! sessions/<name>/session.json    the creation request (kind, options, policy), written once
//! sessions/<name>/owner           the label of the token that created it (when there was one)
//! sessions/<name>/snapshot.json   the last snapshot with its checksum (written to a temporary
//!                                 file, fsynced, renamed; see `snapshot_file`)
//! sessions/<name>/journal.log     checksummed entries since that snapshot (see `log`)
//! sessions/<name>/epoch-<n>       in a fleet: ownership claims; the files above are then
//!                                 snapshot-<n>.json and journal-<n>.log (see `takeover`)
//! sessions/.deleted-<name>-<n>/   a deleted session's directory, renamed before it is removed
//! ```
//!
//! A directory is never overwritten: creating a session whose name has a directory (one that
//! could not be loaded at start, say) is refused, and a creation that fails part way removes
//! what it made. A deletion first renames the directory to a tombstone and fsyncs `sessions/`
//! (from then on the session is gone, whatever happens), then removes the tombstone; one left by
//! a crash or a failed removal is removed at the next start.
//!
//! Why files and not an embedded store: the journal is append-only with one writer per session
//! and is only ever read whole at start; a checksummed record file does exactly that with one
//! `write` and one `fdatasync` per batch, and its failure modes (a torn tail) are handled in
//! thirty lines. A key-value store (sled, redb, RocksDB) would add its own log under ours, a
//! compaction policy, and a build cost, and buy nothing we read back by key.
//!
//! Layer 7: imports `api` (entries are its wire types); never `session` or above.

pub mod compact;
pub mod epoch;
pub mod group_commit;
pub mod log;
mod snapshot_file;
mod takeover;

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{self, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

pub use compact::Compaction;
pub use log::{read_log, Fsync, LogWriter};

use crate::api::fusion::FusionMessage;
use crate::api::wire::{AutoOptimize, Batch, CreateSession, FactorId, FactorSpec, VariableSpec};
use crate::problem::Key;

/// `journal` in the server configuration.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct JournalConfig {
    /// Keep sessions on disk at all (off: sessions live in memory only, as before).
    pub enabled: bool,
    pub fsync: Fsync,
    /// Period of the background fsync under `fsync: interval`.
    pub interval_ms: u64,
    /// Write a snapshot and start a new journal after this many entries.
    pub snapshot_every: u64,
    /// And, once a session's snapshot exceeds 1 MiB, only when its journal has grown to this
    /// share of the last snapshot (0: every `snapshot_every` entries, whatever their size).
    pub snapshot_journal_share: f64,
}

impl Default for JournalConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            fsync: Fsync::Always,
            interval_ms: 100,
            snapshot_every: 2000,
            snapshot_journal_share: 0.25,
        }
    }
}

/// One journal entry: an accepted update, as it must be replayed.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(tag = "op", rename_all = "snake_case")]
pub enum Entry {
    /// A batch with every variable's initial value filled in (predicted ones included), so the
    /// replay does not depend on the estimate it happens to be replayed on.
    Batch {
        sequence: u64,
        batch: Batch,
    },
    AutoOptimize {
        auto_optimize: AutoOptimize,
    },
    /// A merge of robots' components the batch `sequence` (the entry before) completed.
    Merge {
        sequence: u64,
        merge: crate::api::robots::MergeRecord,
    },
    /// Fusion messages a sliding window accepted, in order.
    Fusion {
        messages: Vec<FusionMessage>,
    },
    /// Factor types declared in a running session (those of its creation are in its record).
    FactorTypes {
        factor_types: Vec<crate::factors::expression::FactorTypeDefinition>,
    },
}

/// The estimate and the problem at `sequence`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Snapshot {
    pub sequence: u64,
    pub next_factor_id: FactorId,
    pub auto_optimize: AutoOptimize,
    /// Every variable with its current estimate.
    pub variables: Vec<VariableSpec>,
    /// Every live factor with its id, in its wire form.
    pub factors: Vec<(FactorId, FactorSpec)>,
    /// Exactly-once ingest: every producer's progress and its latest acknowledgements.
    #[serde(default)]
    pub producers: Vec<ProducerRecord>,
    /// Every factor type declared at `sequence` (compiled before the factors are restored).
    #[serde(default)]
    pub factor_types: Vec<crate::factors::expression::FactorTypeDefinition>,
    /// A bundle adjustment's given values (what its client sent for each variable, and
    /// guesses since), where its restarts start from; `variables` hold the estimate. Absent in
    /// snapshots of other kinds, and in those written before it was kept.
    #[serde(default)]
    pub given: Vec<(Key, Vec<f64>)>,
}

/// A producer's progress in a session, as a snapshot keeps it (the journal's batches after the
/// snapshot carry the rest).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct ProducerRecord {
    pub producer: String,
    pub accepted_through: u64,
    /// Its latest acknowledgements, oldest first.
    pub acks: Vec<KeptAck>,
}

/// What a repeat of a producer's batch is answered with: its original acknowledgement.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct KeptAck {
    pub producer_seq: u64,
    /// Its session sequence.
    pub sequence: u64,
    /// Its factor ids as runs `[first, count]` (a batch's ids are consecutive).
    pub factor_ids: Vec<[u64; 2]>,
    pub predicted: Vec<crate::problem::Key>,
}

/// A [`Snapshot`] written from borrowed parts (the factors straight from the map that keeps
/// them): the same JSON, without copying a large session to write it.
#[derive(Serialize)]
pub struct SnapshotOut<'a> {
    pub sequence: u64,
    pub next_factor_id: FactorId,
    pub auto_optimize: AutoOptimize,
    pub variables: &'a [VariableSpec],
    #[serde(serialize_with = "factors_in_order")]
    pub factors: &'a BTreeMap<FactorId, FactorSpec>,
    pub producers: &'a [ProducerRecord],
    #[serde(skip_serializing_if = "<[_]>::is_empty")]
    pub factor_types: &'a [crate::factors::expression::FactorTypeDefinition],
    #[serde(skip_serializing_if = "<[_]>::is_empty")]
    pub given: &'a [(Key, &'a [f64])],
}

/// `[[id, spec], ...]` in id order, as `Vec<(FactorId, FactorSpec)>` is written.
fn factors_in_order<S: serde::Serializer>(
    factors: &&BTreeMap<FactorId, FactorSpec>,
    serializer: S,
) -> Result<S::Ok, S::Error> {
    serializer.collect_seq(factors.iter())
}

/// Who a session directory's session is: read at start, before it is listed.
#[derive(Debug)]
pub struct Identity {
    pub request: CreateSession,
    pub owner: Option<String>,
}

/// What a session directory holds to rebuild its session from: read in the background.
#[derive(Debug)]
pub struct Recovered {
    pub snapshot: Option<Snapshot>,
    /// Bytes of the snapshot's file (0 without one).
    pub snapshot_bytes: usize,
    pub entries: Vec<Entry>,
    /// Bytes of a torn journal tail that were cut off.
    pub truncated_bytes: u64,
    /// The journal is damaged (a bad record that is not a torn tail, see `log`): `entries` are
    /// those before the damage, the file is unchanged, and this says where (file and byte
    /// offset) and why it is damage.
    pub corruption: Option<String>,
}

#[derive(Debug, thiserror::Error)]
pub enum JournalError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: io::Error },
    #[error("{path}: {message}")]
    Corrupt { path: PathBuf, message: String },
    /// A snapshot whose content does not match the checksum written with it.
    #[error(
        "{path}: checksum mismatch: written with CRC-32 {recorded:08x}, its snapshot now hashes \
         to {computed:08x}: the file was damaged after it was written"
    )]
    SnapshotChecksum {
        path: PathBuf,
        recorded: u32,
        computed: u32,
    },
    /// A snapshot at sequence `u64::MAX`: no batch can follow it without reusing a sequence.
    #[error(
        "{path}: the snapshot is at sequence {max}, the last there is: the next batch would \
         wrap to sequence 0 and reuse acknowledged sequences, and no session gets there by \
         accepting batches (the file was damaged or edited)",
        max = u64::MAX
    )]
    LastSequence { path: PathBuf },
    /// Another instance claimed the ownership epoch first (see `takeover`).
    #[error("{path}: another instance claimed the session's next ownership epoch first")]
    Taken { path: PathBuf },
    /// The ownership epoch this instance holds is over: another instance took the session.
    #[error("{path}: another instance has taken the session over")]
    Superseded { path: PathBuf },
    /// A directory of that name is on disk already (never overwritten).
    #[error("{path} already exists")]
    Exists { path: PathBuf },
    /// A creation failed (`cause`) and its directory could not be removed either.
    #[error("{cause}; removing the unfinished directory failed too: {removal}")]
    RollBackFailed {
        cause: Box<JournalError>,
        removal: Box<JournalError>,
    },
}

/// Where deleted sessions' directories are renamed to (session names never start with `.`).
const TOMBSTONE_PREFIX: &str = ".deleted-";

/// A deleted session's directory under its tombstone name: the deletion is durable already.
#[derive(Debug)]
pub struct Tombstone {
    dir: PathBuf,
}

impl Tombstone {
    /// Removes the directory for good. A failure leaves the tombstone, which the next start
    /// removes.
    pub fn purge(self) -> Result<(), JournalError> {
        std::fs::remove_dir_all(&self.dir).map_err(io_at(&self.dir))
    }
}

fn io_at(path: &Path) -> impl Fn(io::Error) -> JournalError + '_ {
    move |source| JournalError::Io {
        path: path.into(),
        source,
    }
}

/// One session's directory.
#[derive(Debug, Clone)]
pub struct SessionDir {
    dir: PathBuf,
    /// The ownership epoch whose files this writes and reads (see `epoch` and `takeover`):
    /// 0, the unnumbered files, outside a fleet.
    epoch: u64,
}

impl SessionDir {
    pub fn sessions_root(state_dir: &Path) -> PathBuf {
        state_dir.join("sessions")
    }

    /// Creates the directory of a new session and records how it was created. A directory of
    /// that name already on disk is never touched: [`JournalError::Exists`]. When a later step
    /// fails, the new directory is removed again, so a refused creation leaves nothing behind.
    pub fn create(
        state_dir: &Path,
        name: &str,
        request: &CreateSession,
        owner: Option<&str>,
    ) -> Result<Self, JournalError> {
        let root = Self::sessions_root(state_dir);
        std::fs::create_dir_all(&root).map_err(io_at(&root))?;
        let dir = root.join(name);
        // `create_dir`, not `create_dir_all`: it fails on an existing directory, atomically.
        match std::fs::create_dir(&dir) {
            Ok(()) => {}
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists => {
                return Err(JournalError::Exists { path: dir })
            }
            Err(e) => return Err(io_at(&dir)(e)),
        }
        let created = Self { dir, epoch: 0 };
        let fill = || -> Result<(), JournalError> {
            if let Some(owner) = owner {
                write_atomically(&created.dir.join("owner"), &[owner.as_bytes()])?;
            }
            // Written last: a directory without it is an unfinished creation, not listed.
            let text = serde_json::to_vec_pretty(request).expect("serialisable");
            write_atomically(&created.dir.join("session.json"), &[&text])?;
            sync_dir(&root)
        };
        match fill() {
            Ok(()) => Ok(created),
            Err(e) => Err(created.roll_back(e)),
        }
    }

    /// Removes the directory of a creation that failed part way; returns `cause`, with the
    /// removal's own failure added to it.
    pub fn roll_back(&self, cause: JournalError) -> JournalError {
        // `remove_dir` first: it needs no file descriptor, and running out of those (EMFILE) is
        // one way a creation fails. The fsync after it is best effort: the directory has no
        // `session.json` yet, so it would not come back as a session.
        let removed = std::fs::remove_dir(&self.dir)
            .or_else(|_| std::fs::remove_dir_all(&self.dir))
            .map_err(io_at(&self.dir));
        if removed.is_ok() {
            let _ = sync_dir(self.dir.parent().unwrap_or(&self.dir));
        }
        match removed {
            Ok(()) => cause,
            Err(removal) => JournalError::RollBackFailed {
                cause: Box::new(cause),
                removal: Box::new(removal),
            },
        }
    }

    /// Makes the deletion of session `name` durable: renames its directory to a tombstone and
    /// fsyncs `sessions/`. `None` when it has no directory (nothing to delete).
    pub fn bury(state_dir: &Path, name: &str) -> Result<Option<Tombstone>, JournalError> {
        let root = Self::sessions_root(state_dir);
        let dir = root.join(name);
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos());
        let tombstone = root.join(format!("{TOMBSTONE_PREFIX}{name}-{nanos}"));
        match std::fs::rename(&dir, &tombstone) {
            Ok(()) => {}
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(io_at(&dir)(e)),
        }
        sync_dir(&root)?;
        Ok(Some(Tombstone { dir: tombstone }))
    }

    /// Removes the tombstones a crash or a failed removal left (their sessions were deleted);
    /// returns the paths it could not remove, with why.
    pub fn finish_deletions(state_dir: &Path) -> Vec<JournalError> {
        let root = Self::sessions_root(state_dir);
        let Ok(entries) = std::fs::read_dir(&root) else {
            return Vec::new();
        };
        entries
            .flatten()
            .filter(|e| {
                e.file_name()
                    .to_string_lossy()
                    .starts_with(TOMBSTONE_PREFIX)
            })
            .filter_map(|e| {
                let dir = e.path();
                tracing::info!("removing {} (a session deleted earlier)", dir.display());
                Tombstone { dir }.purge().err()
            })
            .collect()
    }

    /// The name of every session directory on disk, loadable or not (tombstones excluded).
    pub fn names_on_disk(state_dir: &Path) -> Result<Vec<String>, JournalError> {
        let root = Self::sessions_root(state_dir);
        let entries = match std::fs::read_dir(&root) {
            Ok(e) => e,
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(io_at(&root)(e)),
        };
        let mut names = Vec::new();
        for entry in entries {
            let entry = entry.map_err(io_at(&root))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            if entry.path().is_dir() && !name.starts_with(TOMBSTONE_PREFIX) {
                names.push(name);
            }
        }
        Ok(names)
    }

    /// The directories of every session under `state_dir`, by name.
    pub fn list(state_dir: &Path) -> Result<Vec<(String, Self)>, JournalError> {
        let root = Self::sessions_root(state_dir);
        let entries = match std::fs::read_dir(&root) {
            Ok(e) => e,
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(io_at(&root)(e)),
        };
        let mut out = Vec::new();
        for entry in entries {
            let entry = entry.map_err(io_at(&root))?;
            let path = entry.path();
            let name = entry.file_name().to_string_lossy().into_owned();
            if path.join("session.json").exists() && !name.starts_with(TOMBSTONE_PREFIX) {
                out.push((
                    name,
                    Self {
                        dir: path,
                        epoch: 0,
                    },
                ));
            }
        }
        out.sort_by(|a, b| a.0.cmp(&b.0));
        Ok(out)
    }

    pub fn path(&self) -> &Path {
        &self.dir
    }

    fn journal_path(&self) -> PathBuf {
        segment_file(&self.dir, "journal", "log", self.epoch)
    }

    fn snapshot_path(&self) -> PathBuf {
        segment_file(&self.dir, "snapshot", "json", self.epoch)
    }

    fn history_path(&self) -> PathBuf {
        self.dir.join("history.json")
    }

    pub fn open_journal(&self, fsync: Fsync) -> Result<LogWriter, JournalError> {
        let path = self.journal_path();
        LogWriter::open(&path, fsync).map_err(io_at(&path))
    }

    /// Reads the creation request and the owner: what listing the session needs.
    pub fn load_identity(&self) -> Result<Identity, JournalError> {
        let request_path = self.dir.join("session.json");
        let text = std::fs::read(&request_path).map_err(io_at(&request_path))?;
        let request: CreateSession =
            serde_json::from_slice(&text).map_err(|e| JournalError::Corrupt {
                path: request_path.clone(),
                message: e.to_string(),
            })?;
        let owner_path = self.dir.join("owner");
        let owner = match std::fs::read_to_string(&owner_path) {
            Ok(text) => Some(text),
            Err(e) if e.kind() == io::ErrorKind::NotFound => None,
            Err(e) => return Err(io_at(&owner_path)(e)),
        };
        Ok(Identity { request, owner })
    }

    /// Reads the snapshot and the journal after it (cutting a torn tail, keeping a damaged
    /// journal as it is): the session's state, possibly large.
    pub fn load_state(&self) -> Result<Recovered, JournalError> {
        let snapshot_path = self.snapshot_path();
        let (snapshot, snapshot_bytes) = match std::fs::read(&snapshot_path) {
            Ok(bytes) => (
                Some(snapshot_file::decode(&snapshot_path, &bytes)?),
                bytes.len(),
            ),
            Err(e) if e.kind() == io::ErrorKind::NotFound => (None, 0),
            Err(e) => return Err(io_at(&snapshot_path)(e)),
        };
        let journal = self.journal_path();
        let contents = read_log(&journal).map_err(io_at(&journal))?;
        let mut entries = Vec::with_capacity(contents.records.len());
        for (i, record) in contents.records.iter().enumerate() {
            // The checksum matched, so this is what was written: a decoding failure is a bug or
            // a format change, not a torn write, and must not be skipped silently.
            entries.push(
                serde_json::from_slice(record).map_err(|e| JournalError::Corrupt {
                    path: journal.clone(),
                    message: format!("entry {i}: {e}"),
                })?,
            );
        }
        Ok(Recovered {
            snapshot,
            snapshot_bytes,
            entries,
            truncated_bytes: contents.truncated_bytes,
            corruption: contents
                .corruption
                .map(|c| format!("{}: {c}", journal.display())),
        })
    }

    /// Makes a serialised snapshot (a [`SnapshotOut`]) durable with its checksum (see
    /// `snapshot_file`): written to a temporary file, fsynced, renamed over the last one. The
    /// journal is compacted afterwards (see [`Compaction`]); a crash between the two leaves
    /// records the snapshot already holds, which replay skips by sequence.
    pub fn write_snapshot(&self, bytes: &[u8]) -> Result<(), JournalError> {
        let head = snapshot_file::envelope_head(bytes);
        write_atomically(&self.snapshot_path(), &[&head, bytes, snapshot_file::CLOSE])
    }

    /// Replaces the session's history file (`history.json`, see `session::history`): written
    /// to a temporary file and renamed over the last one, not fsynced. The history is the
    /// operators' view of the stream, rewritten every second while the session is busy; a
    /// killed process leaves the last whole file (the kernel writes it out), and a power loss
    /// costs at most a timeline, never an accepted batch. Fsyncing it would queue ahead of the
    /// journals' fsyncs that acknowledgements wait for.
    pub fn write_history(&self, bytes: &[u8]) -> Result<(), JournalError> {
        let path = self.history_path();
        let tmp = path.with_extension("tmp");
        std::fs::write(&tmp, bytes).map_err(io_at(&tmp))?;
        std::fs::rename(&tmp, &path).map_err(io_at(&path))
    }

    /// The history file's bytes (`None` when the session has none yet).
    pub fn load_history(&self) -> Result<Option<Vec<u8>>, JournalError> {
        let path = self.history_path();
        match std::fs::read(&path) {
            Ok(bytes) => Ok(Some(bytes)),
            Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(io_at(&path)(e)),
        }
    }
}

/// `<stem>.<ext>` for epoch 0, `<stem>-<epoch>.<ext>` after (see `takeover`).
fn segment_file(dir: &Path, stem: &str, ext: &str, epoch: u64) -> PathBuf {
    match epoch {
        0 => dir.join(format!("{stem}.{ext}")),
        n => dir.join(format!("{stem}-{n}.{ext}")),
    }
}

/// Bytes written between two fdatasyncs of a large file: the disk is never handed a whole
/// snapshot to flush at once, which would hold up the journals' fsyncs (the acknowledgements)
/// behind it for as long. With 4 MiB pieces (a flush of ~7 ms here) the 40 MB snapshots of a
/// 100 000-pose session held acknowledgements 5–8 ms in the updates right after each began;
/// 1 MiB bounds such a wait at a quarter, and the snapshot took no longer (0.27–0.32 s).
const SYNC_PIECE: usize = 1 << 20;

/// Writes `parts`, one after the other, to `path` so that a crash leaves either the old or the
/// new content.
fn write_atomically(path: &Path, parts: &[&[u8]]) -> Result<(), JournalError> {
    let tmp = path.with_extension("tmp");
    let mut file = File::create(&tmp).map_err(io_at(&tmp))?;
    let mut unsynced = 0;
    for piece in parts.iter().flat_map(|part| part.chunks(SYNC_PIECE)) {
        if unsynced >= SYNC_PIECE {
            file.sync_data().map_err(io_at(&tmp))?;
            unsynced = 0;
        }
        file.write_all(piece).map_err(io_at(&tmp))?;
        unsynced += piece.len();
    }
    file.sync_all().map_err(io_at(&tmp))?;
    std::fs::rename(&tmp, path).map_err(io_at(path))?;
    sync_dir(path.parent().expect("a file in a directory"))
}

fn sync_dir(dir: &Path) -> Result<(), JournalError> {
    File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(io_at(dir))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_snapshot_written_from_borrowed_parts_reads_back_as_a_snapshot() {
        let factor: FactorSpec = serde_json::from_value(serde_json::json!({"type": "between_se2",
            "keys": [0, 1], "measurement": [1, 0, 0], "sigmas": [1, 1, 1]}))
        .unwrap();
        let factors = BTreeMap::from([(7, factor.clone()), (3, factor)]);
        let variables: Vec<VariableSpec> = serde_json::from_value(serde_json::json!([
            {"key": 0, "kind": "se2", "value": [0, 0, 0], "fixed": true},
            {"key": 1, "kind": "se2", "value": [1, 0, 0]}]))
        .unwrap();
        let bytes = serde_json::to_vec(&SnapshotOut {
            sequence: 12,
            next_factor_id: 8,
            auto_optimize: AutoOptimize::Manual {},
            variables: &variables,
            factors: &factors,
            producers: &[],
            factor_types: &[],
            given: &[(1, &[0.5, 0.0, 0.0])],
        })
        .unwrap();
        let read: Snapshot = serde_json::from_slice(&bytes).unwrap();
        assert_eq!((read.sequence, read.next_factor_id), (12, 8));
        assert_eq!(read.given, [(1, vec![0.5, 0.0, 0.0])]);
        assert_eq!(read.factors.iter().map(|f| f.0).collect::<Vec<_>>(), [3, 7]);
        assert_eq!(read.variables.len(), 2);
        assert!(read.variables[0].fixed);
        assert_eq!(read.factors[1].1.keys, [0, 1]);
    }
}
