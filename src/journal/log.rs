//! A checksummed append-only record file.
//!
//! Each record is `[payload length: u32 LE][CRC-32 of the payload: u32 LE][payload]`. A crash in
//! the middle of an append leaves a record whose length runs past the end of the file, or some of
//! whose bytes still read as the zeros they were written over (a sector the disk had not written,
//! or the end of a write cut short). Reading stops at the first bad record and, when it is such a
//! torn tail, the file is truncated there, so it is dropped, never misread. Everything before it
//! was acknowledged only after its append (and, under `fsync always`, its fsync) returned.
//!
//! A bad record with an intact record anywhere after it is not a torn tail: an append only ever
//! tears the last record, so what follows was acknowledged and the file was damaged later (a bad
//! sector, a stray write). Nor is a last record that was written whole (its length fits the file,
//! none of its sectors and not its last byte reads as zeros) but fails its checksum: under `fsync
//! always` it was acknowledged. Cutting either would drop acknowledged records without a trace,
//! so the file is then left exactly as it is and the damage is reported ([`Corruption`], see
//! `read`). A damaged length field of the last record can still pass for a torn tail: the record
//! it describes runs past the file or into the zeros after it, as a torn one does.
//!
//! The file is grown ahead of the records, with zeros written for real (64 KiB, then by its own
//! size up to 1 MiB at a time), and records are written into that space at their offset. An
//! fdatasync after an append that changes the file's size also commits the size to the file
//! system's journal; after a write into space already written it flushes the data alone. On this
//! machine's ext4 (2 000 writes plus fdatasync, five runs) a 300-byte append took 138–184 µs on
//! average against 94–112 µs into zeros written beforehand (p99 247–301 against 159–195 µs, CPU
//! 59–75 against 40–49 µs). Space reserved with `fallocate` is "unwritten" until written, and its
//! conversion is again a journalled change: with 4 KiB records, 140–145 µs there (appends:
//! 145–152 µs) against 102–129 µs into zeros. Since empty records are never written, a zero length
//! field is the end of the records: zeros after the last record are the grown space, neither a torn
//! tail nor damage.

mod read;

use std::fs::{File, OpenOptions};
use std::io;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use super::group_commit::{Durability, Ticket};

const HEADER: usize = 8;
/// No record is larger (a batch is bounded by the request body limit); a larger length field is
/// a torn or corrupt header.
pub const MAX_RECORD: usize = 1 << 30;
/// How far the file is first grown ahead of its records; later it grows by its own size, up to
/// [`MAX_GROWTH`], so a session that writes little keeps a small file and a busy one grows the
/// file once in thousands of appends.
const FIRST_GROWTH: u64 = 64 << 10;
const MAX_GROWTH: u64 = 1 << 20;

pub use read::{read_log, Corruption, LogContents};

/// When appends reach the disk.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Fsync {
    /// fsync (fdatasync) before every acknowledgement: an acknowledged batch survives power loss.
    Always,
    /// fsync every `journal.interval_ms` in the background: a crash of the process loses
    /// nothing (the data is in the OS), power loss at most that interval.
    Interval,
    /// Never fsync explicitly: the OS writes back when it likes (survives process crashes).
    Never,
}

/// The writing end of one record file.
#[derive(Debug)]
pub struct LogWriter {
    file: Arc<File>,
    path: PathBuf,
    fsync: Fsync,
    /// Where the records end: the next record is written here.
    bytes: u64,
    /// The file's size: zeros from `bytes` to here (see the module doc).
    allocated: u64,
    records: u64,
    /// A failed write left part of a record that could not be cut off: nothing may follow it.
    torn: bool,
    /// Under `fsync always`: the records written and made durable (`group_commit`).
    durability: Arc<Durability>,
}

impl LogWriter {
    /// Opens `path` for appending (creating it), after [`read_log`] has cut any torn tail: the
    /// next record goes after the last one, over the zeros the file was grown by.
    pub fn open(path: &Path, fsync: Fsync) -> io::Result<Self> {
        // Not in append mode: records are written at their offset, before the file's end.
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(path)?;
        let allocated = file.metadata()?.len();
        let bytes = end_of_records(&file, allocated)?;
        let file = Arc::new(file);
        Ok(Self {
            durability: Durability::new(Arc::clone(&file)),
            file,
            path: path.into(),
            fsync,
            bytes,
            allocated,
            records: 0,
            torn: false,
        })
    }

    /// Appends one record; returns how long the fsync took (zero when the policy skips it).
    pub fn append(&mut self, payload: &[u8]) -> io::Result<Duration> {
        self.write(payload)?;
        self.sync()
    }

    /// Writes one record without the fsync the policy asks for: [`Self::sync`] makes it durable,
    /// and nothing may acknowledge it before that returned.
    pub fn write(&mut self, payload: &[u8]) -> io::Result<()> {
        if self.torn {
            return Err(io::Error::other(
                "an earlier write failed part-way and its partial record could not be cut off; \
                 a restart cuts it (it is the file's torn tail)",
            ));
        }
        if payload.len() > MAX_RECORD {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("record of {} bytes exceeds {MAX_RECORD}", payload.len()),
            ));
        }
        if payload.is_empty() {
            // Its zero length field would read as the end of the records.
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                "an empty record cannot be written",
            ));
        }
        let mut frame = Vec::with_capacity(HEADER + payload.len());
        frame.extend_from_slice(&(payload.len() as u32).to_le_bytes());
        frame.extend_from_slice(&crc32fast::hash(payload).to_le_bytes());
        frame.extend_from_slice(payload);
        let end = self.bytes + frame.len() as u64;
        if end > self.allocated {
            self.grow(end);
        }
        // One write call per record: a crash leaves a prefix of it, which the checksum catches.
        if let Err(e) = self.file.write_all_at(&frame, self.bytes) {
            // A failed write (a full disk) may have written part of the record. Cut it off: a
            // record appended after it would make it damage followed by intact records, which
            // recovery must not cut (see the module doc), so the session would come back
            // read-only without what was acknowledged after it.
            self.torn = self.file.set_len(self.bytes).is_err();
            self.allocated = self.bytes;
            return Err(e);
        }
        self.bytes = end;
        self.records += 1;
        self.durability.written();
        Ok(())
    }

    /// Under `fsync always`, makes every record written so far durable (sharing one
    /// fdatasync with other waiters, see `group_commit`); returns how long it waited (zero
    /// when the policy skips it).
    pub fn sync(&self) -> io::Result<Duration> {
        match self.last_ticket() {
            Some(ticket) => ticket.wait(),
            None => Ok(Duration::ZERO),
        }
    }

    /// Under `fsync always`: what to wait for, without this writer, until every record written
    /// so far is durable (`None` when the policy skips the fsync).
    pub fn last_ticket(&self) -> Option<Ticket> {
        (self.fsync == Fsync::Always).then(|| self.durability.last())
    }

    /// The records written and made durable through this writer.
    pub fn durability(&self) -> &Durability {
        &self.durability
    }

    /// Grows the file with zeros after `end`, where the record about to be written ends (see the
    /// module doc); the record itself fills the file up to there. Best effort: on a full disk
    /// the record is written as it would be without the zeros, and what was written of them
    /// stays (zeros are the end of the records).
    fn grow(&mut self, end: u64) {
        static ZEROS: [u8; 64 << 10] = [0; 64 << 10];
        let step = self.allocated.clamp(FIRST_GROWTH, MAX_GROWTH);
        let target = end.max(self.allocated + step);
        let mut at = end;
        while at < target {
            let n = (target - at).min(ZEROS.len() as u64);
            if self.file.write_all_at(&ZEROS[..n as usize], at).is_err() {
                break;
            }
            at += n;
        }
        self.allocated = at;
    }

    /// Empties the file (its records are in a durable snapshot now).
    pub fn clear(&mut self) -> io::Result<()> {
        self.file.set_len(0)?;
        self.file.sync_all()?;
        self.bytes = 0;
        self.allocated = 0;
        self.durability.all_durable();
        Ok(())
    }

    /// Writes to `file` from now on: the journal's new file (see `compact`), holding `bytes`
    /// and nothing after them.
    pub(super) fn replace_file(&mut self, file: File, bytes: u64) {
        self.file = Arc::new(file);
        self.bytes = bytes;
        self.allocated = bytes;
        self.durability.switched(Arc::clone(&self.file));
    }

    /// The new file holds every record written so far, fdatasynced, and its directory entry
    /// is durable (`Compaction::finish`): their writers need no fdatasync of their own.
    pub(super) fn copy_made_durable(&self) {
        self.durability.all_durable();
    }

    /// The file handle, for a background syncer under `Fsync::Interval`.
    pub fn handle(&self) -> Arc<File> {
        Arc::clone(&self.file)
    }

    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Records appended through this writer.
    pub fn records(&self) -> u64 {
        self.records
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// Where the records of `file` (`size` bytes, its torn tail cut) end: the first zero length
/// field, or the first record that would run past the file's end. Reads the headers only.
fn end_of_records(file: &File, size: u64) -> io::Result<u64> {
    let mut at = 0;
    let mut header = [0u8; HEADER];
    while at + HEADER as u64 <= size {
        file.read_exact_at(&mut header, at)?;
        let len = u32::from_le_bytes([header[0], header[1], header[2], header[3]]) as u64;
        let end = at + HEADER as u64 + len;
        if len == 0 || end > size {
            break;
        }
        at = end;
    }
    Ok(at)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A write that fails part-way (here: past the file size limit, as on a full disk) leaves
    /// no partial record: the next record follows the last whole one and the file reads whole.
    /// The limit is the process's, so the writing runs in a child process: this test binary,
    /// running [`write_past_the_file_size_limit`] alone.
    #[test]
    fn a_write_that_fails_part_way_leaves_no_partial_record() {
        let path = temp("partial");
        let output = std::process::Command::new(std::env::current_exe().unwrap())
            .args([
                "--exact",
                "journal::log::tests::write_past_the_file_size_limit",
            ])
            .args(["--include-ignored", "--nocapture", "--test-threads=1"])
            .env("FACTORD_PARTIAL_WRITE_AT", &path)
            .output()
            .unwrap();
        let stdout = String::from_utf8_lossy(&output.stdout);
        assert!(
            output.status.success() && stdout.contains("1 passed"),
            "{stdout}\n{}",
            String::from_utf8_lossy(&output.stderr)
        );
        let contents = read_log(&path).unwrap();
        assert_eq!(contents.records, [b"first".to_vec(), b"third".to_vec()]);
        assert_eq!((contents.truncated_bytes, contents.corruption), (0, None));
    }

    /// The child of the test above: a record, a second one that fails past a file size limit
    /// in the middle of it, the limit lifted, a third record.
    #[test]
    #[ignore = "run by a_write_that_fails_part_way_leaves_no_partial_record in a child process"]
    fn write_past_the_file_size_limit() {
        let path = PathBuf::from(std::env::var_os("FACTORD_PARTIAL_WRITE_AT").unwrap());
        let mut w = LogWriter::open(&path, Fsync::Never).unwrap();
        w.append(b"first").unwrap();
        let limit = |soft: libc::rlim_t| {
            let mut l = libc::rlimit {
                rlim_cur: 0,
                rlim_max: 0,
            };
            // SAFETY: plain system calls on a local struct.
            unsafe {
                assert_eq!(libc::getrlimit(libc::RLIMIT_FSIZE, &mut l), 0);
                l.rlim_cur = soft.min(l.rlim_max);
                assert_eq!(libc::setrlimit(libc::RLIMIT_FSIZE, &l), 0);
            }
        };
        // SAFETY: ignoring SIGXFSZ makes a write past the limit fail with EFBIG instead.
        unsafe { libc::signal(libc::SIGXFSZ, libc::SIG_IGN) };
        limit(w.bytes() + 20);
        let second = vec![b'x'; 100];
        assert!(w.append(&second).is_err(), "the write past the limit fails");
        assert_eq!(std::fs::metadata(&path).unwrap().len(), w.bytes());
        limit(libc::RLIM_INFINITY);
        w.append(b"third").unwrap();
    }

    pub(super) fn temp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("factord-log-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir.join("journal.log")
    }

    #[test]
    fn the_zeros_the_file_grew_by_end_the_records_and_are_kept() {
        let path = temp("grown");
        let mut w = LogWriter::open(&path, Fsync::Always).unwrap();
        for i in 0..3 {
            w.append(format!("record {i}").as_bytes()).unwrap();
        }
        let end = w.bytes();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(bytes.len() as u64, FIRST_GROWTH);
        assert!(bytes[end as usize..].iter().all(|&b| b == 0));
        let read = read_log(&path).unwrap();
        assert_eq!(read.records.len(), 3);
        assert_eq!((read.truncated_bytes, read.corruption), (0, None));
        assert_eq!(std::fs::read(&path).unwrap(), bytes, "the zeros are kept");
        // A writer opened again goes on after the last record, into the zeros.
        drop(w);
        let mut w = LogWriter::open(&path, Fsync::Always).unwrap();
        assert_eq!(w.bytes(), end);
        w.append(b"record 3").unwrap();
        assert_eq!(std::fs::metadata(&path).unwrap().len(), bytes.len() as u64);
        // Past the zeros the file grows by its own size, then by at most MAX_GROWTH.
        let big = vec![b'x'; 100 << 10];
        let mut sizes = Vec::new();
        for _ in 0..30 {
            w.append(&big).unwrap();
            sizes.push(std::fs::metadata(&path).unwrap().len());
        }
        assert!(sizes
            .windows(2)
            .all(|s| s[1] - s[0] <= MAX_GROWTH + big.len() as u64));
        assert!(*sizes.last().unwrap() - w.bytes() <= MAX_GROWTH);
        let read = read_log(&path).unwrap();
        assert_eq!(read.records.len(), 34);
        assert_eq!((read.truncated_bytes, read.corruption), (0, None));
        // A record torn in the zeros is a torn tail: cut, with the zeros after it.
        let size = std::fs::metadata(&path).unwrap().len();
        let mut frame = 9u32.to_le_bytes().to_vec();
        frame.extend_from_slice(&crc32fast::hash(b"record 34").to_le_bytes());
        frame.extend_from_slice(b"rec");
        w.file.write_all_at(&frame, w.bytes()).unwrap();
        let read = read_log(&path).unwrap();
        assert_eq!(read.records.len(), 34);
        assert_eq!(read.truncated_bytes, size - w.bytes());
        assert_eq!(std::fs::metadata(&path).unwrap().len(), w.bytes());
        // A zeroed header with records after it is damage, not the end.
        let mut bytes = std::fs::read(&path).unwrap();
        bytes[HEADER + 8..2 * HEADER + 8].fill(0);
        std::fs::write(&path, &bytes).unwrap();
        let read = read_log(&path).unwrap();
        assert_eq!(read.records.len(), 1);
        assert!(read.corruption.is_some());
        // An empty record, whose zero length would read as the end, is refused.
        assert!(w.append(b"").is_err());
    }
}
