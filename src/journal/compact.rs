//! Dropping the start of a journal that a snapshot has made redundant, while appends go on.
//!
//! A snapshot taken at journal offset `prefix` holds everything the records before that offset
//! say; the records after it were appended while the snapshot was being written and must stay.
//! The records from `prefix` on are copied to `journal.tmp` and fdatasynced in two steps: most
//! of them without the writer's lock ([`Compaction::copy_until`], as often as wanted; the
//! offsets come from [`LogWriter::bytes`], which counts only whole appends), then, under the
//! writer's lock, whatever was appended since ([`Compaction::finish`]); the copy is renamed over
//! the journal, the directory fsynced, and the writer appends to the new file from then on. The
//! writer's lock covers the last few records and two syncs, not the journal.
//!
//! A crash at any point leaves the old journal (with the snapshot's records still in it: replay
//! skips batches the snapshot holds by their sequence) or the new one; a `journal.tmp` left
//! behind is never read and is overwritten by the next compaction.

use std::fs::{File, OpenOptions};
use std::io::{self, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use super::log::LogWriter;

/// A compaction under way: the journal's records from `prefix` on, copied as far as `copied_to`.
#[derive(Debug)]
pub struct Compaction {
    prefix: u64,
    copied_to: u64,
    /// `journal.tmp`, once something was copied.
    tmp: Option<(File, PathBuf)>,
}

impl Compaction {
    /// A compaction that drops the journal's first `prefix` bytes (whole records).
    pub fn new(prefix: u64) -> Self {
        Self {
            prefix,
            copied_to: prefix,
            tmp: None,
        }
    }

    /// Copies the journal's bytes `[copied so far, upto)` to `journal.tmp`, beside `journal`.
    /// `upto` must be a [`LogWriter::bytes`] read after the appends it covers returned.
    pub fn copy_until(&mut self, journal: &Path, upto: u64) -> io::Result<()> {
        if upto <= self.copied_to {
            return Ok(());
        }
        let mut source = File::open(journal)?;
        source.seek(SeekFrom::Start(self.copied_to))?;
        let mut bytes = Vec::with_capacity((upto - self.copied_to) as usize);
        (&mut source)
            .take(upto - self.copied_to)
            .read_to_end(&mut bytes)?;
        if bytes.len() as u64 != upto - self.copied_to {
            return Err(io::Error::new(
                io::ErrorKind::UnexpectedEof,
                format!(
                    "{}: {} bytes expected from offset {}, {} read",
                    journal.display(),
                    upto - self.copied_to,
                    self.copied_to,
                    bytes.len()
                ),
            ));
        }
        let tmp = match &mut self.tmp {
            Some((file, _)) => file,
            None => {
                // Not in append mode: the writer writes its records at their offsets, before
                // the zeros it grows the file by (see `log`). A copy a crash left behind is
                // removed first.
                let path = journal.with_extension("tmp");
                match std::fs::remove_file(&path) {
                    Err(e) if e.kind() != io::ErrorKind::NotFound => return Err(e),
                    _ => {}
                }
                let file = OpenOptions::new()
                    .create_new(true)
                    .read(true)
                    .write(true)
                    .open(&path)?;
                &mut self.tmp.insert((file, path)).0
            }
        };
        tmp.write_all(&bytes)?;
        // Made durable here, so that little is left to sync under the writer's lock.
        tmp.sync_data()?;
        self.copied_to = upto;
        Ok(())
    }

    /// Under the writer's lock: copies what was appended since, and makes the copy the journal
    /// (`journal`'s writer appends to it from now on). Nothing copied and nothing appended since
    /// the snapshot: the journal is emptied in place. On an error before the rename the journal
    /// is unchanged (it holds everything, the snapshot's records included).
    pub fn finish(mut self, journal: &mut LogWriter) -> io::Result<()> {
        let path = journal.path().to_path_buf();
        let end = journal.bytes();
        if end < self.prefix {
            return Err(io::Error::other(format!(
                "{}: the journal has {end} bytes, fewer than the snapshot's {}",
                path.display(),
                self.prefix
            )));
        }
        if self.tmp.is_none() && end == self.prefix {
            return journal.clear();
        }
        self.copy_until(&path, end)?;
        let Some((file, tmp)) = self.tmp.take() else {
            unreachable!("copy_until made it: end > prefix here")
        };
        std::fs::rename(&tmp, &path)?;
        // From here on the directory names the new file: the writer must append there whatever
        // the directory's fsync says.
        journal.replace_file(file, end - self.prefix);
        File::open(path.parent().expect("a journal in a directory"))?.sync_all()?;
        journal.copy_made_durable();
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::journal::log::{read_log, Fsync};

    fn journal(name: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("factord-compact-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir.join("journal.log")
    }

    fn records(path: &Path) -> Vec<String> {
        read_log(path)
            .unwrap()
            .records
            .into_iter()
            .map(|r| String::from_utf8(r).unwrap())
            .collect()
    }

    #[test]
    fn records_appended_during_a_snapshot_survive_its_compaction() {
        let path = journal("during");
        let mut w = LogWriter::open(&path, Fsync::Always).unwrap();
        for i in 0..5 {
            w.append(format!("before {i}").as_bytes()).unwrap();
        }
        let mut c = Compaction::new(w.bytes());
        w.append(b"during 0").unwrap();
        c.copy_until(&path, w.bytes()).unwrap();
        w.append(b"during 1").unwrap();
        c.finish(&mut w).unwrap();
        w.append(b"after").unwrap();
        assert_eq!(records(&path), ["during 0", "during 1", "after"]);
        assert!(!path.with_extension("tmp").exists());
        // The writer counts the new file's bytes: a second compaction drops exactly its prefix.
        let mut c = Compaction::new(w.bytes() - (8 + "after".len() as u64));
        c.copy_until(&path, w.bytes()).unwrap();
        c.finish(&mut w).unwrap();
        assert_eq!(records(&path), ["after"]);
    }

    #[test]
    fn nothing_appended_since_empties_the_journal_in_place() {
        let path = journal("idle");
        let mut w = LogWriter::open(&path, Fsync::Never).unwrap();
        w.append(b"one").unwrap();
        let c = Compaction::new(w.bytes());
        c.finish(&mut w).unwrap();
        assert_eq!(std::fs::metadata(&path).unwrap().len(), 0);
        w.append(b"two").unwrap();
        assert_eq!(records(&path), ["two"]);
    }

    #[test]
    fn a_journal_shorter_than_the_snapshot_is_refused_and_left_alone() {
        let path = journal("short");
        let mut w = LogWriter::open(&path, Fsync::Never).unwrap();
        w.append(b"one").unwrap();
        let c = Compaction::new(w.bytes() + 1);
        assert!(c.finish(&mut w).is_err());
        assert_eq!(records(&path), ["one"]);
    }
}
