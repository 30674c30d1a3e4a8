//! A fleet's session directory passing from one instance to the next, safely even when the
//! last holder only stopped answering (SIGSTOP, a frozen host) and may resume any time.
//!
//! Every instance that loads a session in a fleet first claims the next ownership epoch of its
//! directory (`epoch`: `epoch-<n>`, created once, atomically, by exactly one claimant) and
//! writes that epoch's files only: `journal-<n>.log` and `snapshot-<n>.json`. Taking over
//! epoch `n` from epoch `m` (the latest whose journal exists):
//!
//! 1. claim `epoch-<n>` (from here on the holder of `m` acknowledges nothing: it checks the
//!    fence, [`SessionDir::superseded`], after every fsync and before every acknowledgement);
//! 2. copy `journal-<m>.log` to a temporary file, then `snapshot-<m>.json` to `snapshot-<n>.json`
//!    (the journal first: a snapshot taken meanwhile is newer than the journal's start, and
//!    replay skips what it holds by sequence, so the pair is always consistent);
//! 3. fsync, and rename the copy to `journal-<n>.log`, which marks epoch `n` complete.
//!
//! Why this loses no acknowledged batch: the old holder acknowledged a batch only after its
//! record was written and the fence was checked and open, so before step 1; the copy reads the
//! file after step 1, on the same file system, so it holds that record. Why nothing the old
//! holder does afterwards matters: whatever it writes goes to epoch `m`'s files, and from step 3
//! on every reader (a recovery, a later takeover) reads epoch `n`'s, the latest complete one;
//! its late snapshots and compactions rewrite `m`'s files only. A record the old holder wrote between
//! steps 1 and 2 may be copied although it was refused (503 `ownership_lost`): like a timeout,
//! that refusal says "not acknowledged", not "not applied", and a producer's retry of it is
//! recognised by its producer sequence. A takeover that crashes between steps 1 and 3 leaves a
//! claim without a journal: the next one copies from epoch `m` again (nothing was acknowledged
//! in the unfinished epoch).
//!
//! The session's history (`history.json`, the operators' timeline, not its state) is shared by
//! the epochs: a resumed old holder may rewrite it once before it steps down.
//!
//! Once epoch `n` is complete, the files of the epochs before `m` are removed: no takeover
//! reads them any more (a concurrent one copies from `m` or later), and a stopped holder of
//! one of them writes into files already unlinked. Each session keeps at most two epochs'
//! files; the claims themselves (a few bytes each) stay.
//!
//! The shared file system must show one process's writes to another at once (a local file
//! system, or a cluster file system with that guarantee): the copy relies on it.

use std::fs::File;
use std::io;
use std::path::Path;

use super::{epoch, io_at, segment_file, JournalError, SessionDir};

impl SessionDir {
    /// The ownership epoch whose files this reads and writes.
    pub fn epoch(&self) -> u64 {
        self.epoch
    }

    /// The directory's latest claim: its epoch, holder, and whether it was released.
    pub fn latest_claim(&self) -> Result<Option<(u64, String, bool)>, JournalError> {
        let claim = epoch::current(&self.dir).map_err(io_at(&self.dir))?;
        Ok(claim.map(|(n, holder)| (n, holder, epoch::released(&self.dir, n))))
    }

    /// A new session's directory in a fleet: claims epoch 1 for `holder` (it holds the lock of
    /// the directory it just created, so nobody else can).
    pub fn claim_first(&mut self, holder: &str) -> Result<(), JournalError> {
        if !epoch::claim(&self.dir, 1, holder).map_err(io_at(&self.dir))? {
            return Err(JournalError::Taken {
                path: self.dir.clone(),
            });
        }
        self.epoch = 1;
        Ok(())
    }

    /// Claims the next epoch for `holder` and carries the latest complete epoch's files over
    /// (see the module doc); returns the directory at the new epoch. [`JournalError::Taken`]
    /// when another instance claimed it first.
    pub fn take_over(&self, holder: &str) -> Result<SessionDir, JournalError> {
        let claimed = epoch::current(&self.dir)
            .map_err(io_at(&self.dir))?
            .map_or(0, |(n, _)| n);
        let source = (0..=claimed)
            .rev()
            .find(|&n| n == 0 || segment_file(&self.dir, "journal", "log", n).exists())
            .unwrap_or(0);
        let next = claimed + 1;
        if !epoch::claim(&self.dir, next, holder).map_err(io_at(&self.dir))? {
            return Err(JournalError::Taken {
                path: self.dir.clone(),
            });
        }
        let journal = segment_file(&self.dir, "journal", "log", next);
        let copy = self.dir.join(format!(".journal-{next}.copy"));
        // Only epoch 0's journal may be missing (a session whose journal was never opened);
        // a later epoch is complete only once its journal is in place.
        let from = segment_file(&self.dir, "journal", "log", source);
        copy_synced(&from, &copy, source == 0)?;
        let snapshot = segment_file(&self.dir, "snapshot", "json", source);
        if snapshot.exists() {
            let snapshot_copy = self.dir.join(format!(".snapshot-{next}.copy"));
            copy_synced(&snapshot, &snapshot_copy, false)?;
            let target = segment_file(&self.dir, "snapshot", "json", next);
            std::fs::rename(&snapshot_copy, &target).map_err(io_at(&target))?;
        }
        std::fs::rename(&copy, &journal).map_err(io_at(&journal))?;
        File::open(&self.dir)
            .and_then(|d| d.sync_all())
            .map_err(io_at(&self.dir))?;
        self.remove_epochs_before(source);
        Ok(SessionDir {
            dir: self.dir.clone(),
            epoch: next,
        })
    }

    /// Removes the journals, snapshots and unfinished copies of the epochs before `epoch`
    /// (see the module doc); best effort: what is left is never read.
    fn remove_epochs_before(&self, epoch: u64) {
        let Ok(entries) = std::fs::read_dir(&self.dir) else {
            return;
        };
        for entry in entries.flatten() {
            let name = entry.file_name().to_string_lossy().into_owned();
            let of = match name.as_str() {
                "journal.log" | "snapshot.json" | "journal.tmp" | "snapshot.tmp" => Some(0),
                other => ["journal-", "snapshot-", ".journal-", ".snapshot-"]
                    .iter()
                    .find_map(|prefix| other.strip_prefix(prefix))
                    .and_then(|rest| rest.split('.').next())
                    .and_then(|n| n.parse::<u64>().ok()),
            };
            if of.is_some_and(|n| n < epoch) {
                let _ = std::fs::remove_file(entry.path());
            }
        }
    }

    /// Whether this epoch is over (see `epoch`): nothing may be acknowledged from it.
    pub fn superseded(&self) -> bool {
        epoch::superseded(&self.dir, self.epoch)
    }

    /// Says that this epoch's holder handed the session over cleanly.
    pub fn release(&self) -> Result<(), JournalError> {
        if self.epoch == 0 {
            return Ok(());
        }
        epoch::release(&self.dir, self.epoch).map_err(io_at(&self.dir))
    }
}

/// Copies `from` (absent, when `may_be_absent`: an empty file) to `to`, fsynced.
fn copy_synced(from: &Path, to: &Path, may_be_absent: bool) -> Result<(), JournalError> {
    match std::fs::copy(from, to) {
        Ok(_) => {}
        Err(e) if may_be_absent && e.kind() == io::ErrorKind::NotFound => {
            File::create(to).map_err(io_at(to))?;
        }
        Err(e) => return Err(io_at(from)(e)),
    }
    File::options()
        .write(true)
        .open(to)
        .and_then(|f| f.sync_all())
        .map_err(io_at(to))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::journal::{Fsync, JournalConfig};

    #[test]
    fn a_takeover_carries_every_record_over_and_fences_the_old_epoch() {
        let state = std::env::temp_dir().join(format!("factord-takeover-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&state);
        let request: crate::api::wire::CreateSession =
            serde_json::from_value(serde_json::json!({"session": "t", "kind": "pose_graph_2d"}))
                .unwrap();
        let mut first = SessionDir::create(&state, "t", &request, None).unwrap();
        first.claim_first("a").unwrap();
        let mut old = first.open_journal(JournalConfig::default().fsync).unwrap();
        old.append(b"one").unwrap();
        old.append(b"two").unwrap();
        assert!(!first.superseded());
        let second = first.take_over("b").unwrap();
        assert_eq!(second.epoch(), 2);
        assert!(first.superseded(), "the old holder sees its epoch is over");
        // What the old holder writes now lands where the new one never reads.
        old.append(b"late").unwrap();
        let records = crate::journal::read_log(&second.journal_path()).unwrap();
        assert_eq!(records.records, [b"one".to_vec(), b"two".to_vec()]);
        let mut new = second.open_journal(Fsync::Always).unwrap();
        new.append(b"three").unwrap();
        assert_eq!(second.latest_claim().unwrap(), Some((2, "b".into(), false)));
        // A third takeover starts from the latest epoch, after a clean release.
        second.release().unwrap();
        assert_eq!(second.latest_claim().unwrap(), Some((2, "b".into(), true)));
        let third = second.take_over("c").unwrap();
        let records = crate::journal::read_log(&third.journal_path()).unwrap();
        assert_eq!(records.records.len(), 3);
        // Two epochs' files are kept: epoch 1's journal went with the third takeover.
        assert!(!first.journal_path().exists());
        assert!(second.journal_path().exists());
        std::fs::remove_dir_all(&state).unwrap();
    }
}
