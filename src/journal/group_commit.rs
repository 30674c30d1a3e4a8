//! Group commit for `fsync always`: the writers of one journal wait on one shared fdatasync.
//!
//! A batch's record is written under the session's journal lock, which is then released; the
//! batch waits for its [`Ticket`] (the number of records written up to its own) to be durable.
//! The first waiter to find no fdatasync running becomes the leader: it notes how many records
//! are written now, runs one fdatasync, and marks them all durable, waking every waiter they
//! cover; records written while it ran are covered by the next leader's fdatasync (the classic
//! leader/follower group commit: no timer, no added latency when a journal is idle). A batch is
//! acknowledged only after its own record is covered by an fdatasync that succeeded.
//!
//! Across sessions the grouping is the kernel's: each journal's leader waits on a blocking
//! thread of its own (batches are applied there, not on the async threads), so the fdatasyncs
//! of many sessions run at once, and the block layer merges the cache flushes of those in
//! flight together (on ext4 their journal commits too). One fdatasync for several journals
//! would need `syncfs`, which also flushes every other writer's dirty pages on that file system
//! (snapshots being written, history files, other programs on a shared disk): it would make
//! acknowledgements wait for them.
//!
//! A failed fdatasync fails every waiter it covered and every later one: whether those records
//! reached the disk is unknown (a failed fsync may drop the written pages), and the session
//! becomes read-only (`Session::journal_sync_failed`).

use std::fs::File;
use std::io;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

/// fdatasyncs run by group commit, and the records they made durable, since the start: their
/// ratio is the fsyncs per record (shown in `/metrics`).
static FSYNCS: AtomicU64 = AtomicU64::new(0);
static RECORDS: AtomicU64 = AtomicU64::new(0);

/// The fdatasyncs and the records they covered, since the process started.
pub fn totals() -> (u64, u64) {
    (
        FSYNCS.load(Ordering::Relaxed),
        RECORDS.load(Ordering::Relaxed),
    )
}

/// One journal file's durability (shared by its writer and the batches waiting on it).
#[derive(Debug)]
pub struct Durability {
    state: Mutex<State>,
    synced: Condvar,
}

#[derive(Debug)]
struct State {
    file: Arc<File>,
    /// Records written through the writer, and how many of them are durable.
    written: u64,
    durable: u64,
    /// A leader's fdatasync is running.
    syncing: bool,
    /// An fdatasync failed: nothing written here is made durable any more.
    failed: Option<String>,
    /// fdatasyncs run for this file's records.
    fsyncs: u64,
}

/// A record to wait for: durable once `durable` reaches `record`.
#[derive(Clone, Debug)]
pub struct Ticket {
    of: Arc<Durability>,
    record: u64,
}

impl Durability {
    pub(super) fn new(file: Arc<File>) -> Arc<Self> {
        Arc::new(Self {
            state: Mutex::new(State {
                file,
                written: 0,
                durable: 0,
                syncing: false,
                failed: None,
                fsyncs: 0,
            }),
            synced: Condvar::new(),
        })
    }

    fn state(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// A record was written (under the writer's lock): returns its ticket.
    pub(super) fn written(self: &Arc<Self>) -> Ticket {
        let mut state = self.state();
        state.written += 1;
        Ticket {
            of: Arc::clone(self),
            record: state.written,
        }
    }

    /// The ticket of the last record written (every record so far is durable with it).
    pub(super) fn last(self: &Arc<Self>) -> Ticket {
        Ticket {
            of: Arc::clone(self),
            record: self.state().written,
        }
    }

    /// fdatasyncs run for this journal's records (through this writer).
    pub fn fsyncs(&self) -> u64 {
        self.state().fsyncs
    }

    /// The writer writes to `file` from now on (a compaction's copy): leaders fdatasync it.
    pub(super) fn switched(&self, file: Arc<File>) {
        self.state().file = file;
    }

    /// Every record written so far is durable by other means: a compaction's fdatasynced copy
    /// renamed into place with its directory fsynced, or an emptied journal whose records are
    /// in a snapshot.
    pub(super) fn all_durable(&self) {
        let mut state = self.state();
        state.durable = state.written;
        drop(state);
        self.synced.notify_all();
    }
}

impl Ticket {
    /// Waits until the record is durable, leading an fdatasync when none runs (see the module
    /// doc). Returns how long it waited.
    pub fn wait(&self) -> io::Result<Duration> {
        let start = Instant::now();
        let of = &self.of;
        let mut state = of.state();
        loop {
            if state.durable >= self.record {
                return Ok(start.elapsed());
            }
            if let Some(failed) = &state.failed {
                return Err(io::Error::other(failed.clone()));
            }
            if state.syncing {
                state = of.synced.wait(state).unwrap_or_else(|p| p.into_inner());
                continue;
            }
            state.syncing = true;
            let (file, target, from) = (Arc::clone(&state.file), state.written, state.durable);
            drop(state);
            let synced = file.sync_data();
            state = of.state();
            state.syncing = false;
            match synced {
                Ok(()) => {
                    FSYNCS.fetch_add(1, Ordering::Relaxed);
                    state.fsyncs += 1;
                    RECORDS.fetch_add(target.saturating_sub(from), Ordering::Relaxed);
                    state.durable = state.durable.max(target);
                }
                Err(e) => state.failed = Some(e.to_string()),
            }
            of.synced.notify_all();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::journal::log::{read_log, Fsync, LogWriter};

    /// Many writers of one journal, each waiting for its own record: every record is durable
    /// and read back, and fewer fdatasyncs than records ran (they were grouped).
    #[test]
    fn concurrent_writers_share_fdatasyncs_and_every_record_is_durable() {
        let dir = std::env::temp_dir().join(format!("factord-group-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("journal.log");
        let writer = Arc::new(Mutex::new(LogWriter::open(&path, Fsync::Always).unwrap()));
        let threads: Vec<_> = (0..8)
            .map(|t| {
                let writer = Arc::clone(&writer);
                std::thread::spawn(move || {
                    for i in 0..50 {
                        let ticket = {
                            let mut w = writer.lock().unwrap();
                            w.write(format!("{t}-{i}").as_bytes()).unwrap();
                            w.last_ticket().expect("fsync always")
                        };
                        // Waited for without the writer's lock, as a batch does.
                        ticket.wait().unwrap();
                    }
                })
            })
            .collect();
        for t in threads {
            t.join().unwrap();
        }
        let fsyncs = writer.lock().unwrap().durability().fsyncs();
        assert_eq!(read_log(&path).unwrap().records.len(), 400);
        eprintln!("{fsyncs} fdatasyncs for 400 records of 8 concurrent writers");
        assert!(
            fsyncs < 400,
            "{fsyncs} fdatasyncs for 400 records: none grouped"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
