//! A checksummed append-only record file.
//!
//! Each record is `[payload length: u32 LE][CRC-32 of the payload: u32 LE][payload]`. A crash in
//! the middle of an append leaves a record whose length runs past the end of the file or whose
//! checksum does not match; reading stops at the first such record and the file is truncated
//! there, so a torn tail is dropped, never misread. Everything before it was acknowledged only
//! after its append (and, under `fsync always`, its fsync) returned.

use std::fs::{File, OpenOptions};
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

const HEADER: usize = 8;
/// No record is larger (a batch is bounded by the request body limit); a larger length field is
/// a torn or corrupt header.
pub const MAX_RECORD: usize = 1 << 30;

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
    bytes: u64,
    records: u64,
}

/// What reading a record file found.
#[derive(Debug)]
pub struct LogContents {
    pub records: Vec<Vec<u8>>,
    /// Bytes of a torn or corrupt tail that were cut off.
    pub truncated_bytes: u64,
}

impl LogWriter {
    /// Opens `path` for appending (creating it), after [`read_log`] has cut any torn tail.
    pub fn open(path: &Path, fsync: Fsync) -> io::Result<Self> {
        let file = OpenOptions::new().create(true).append(true).open(path)?;
        let bytes = file.metadata()?.len();
        Ok(Self {
            file: Arc::new(file),
            path: path.into(),
            fsync,
            bytes,
            records: 0,
        })
    }

    /// Appends one record; returns how long the fsync took (zero when the policy skips it).
    pub fn append(&mut self, payload: &[u8]) -> io::Result<Duration> {
        if payload.len() > MAX_RECORD {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("record of {} bytes exceeds {MAX_RECORD}", payload.len()),
            ));
        }
        let mut frame = Vec::with_capacity(HEADER + payload.len());
        frame.extend_from_slice(&(payload.len() as u32).to_le_bytes());
        frame.extend_from_slice(&crc32fast::hash(payload).to_le_bytes());
        frame.extend_from_slice(payload);
        // One write call per record: a crash leaves a prefix of it, which the checksum catches.
        (&*self.file).write_all(&frame)?;
        self.bytes += frame.len() as u64;
        self.records += 1;
        if self.fsync == Fsync::Always {
            let start = Instant::now();
            self.file.sync_data()?;
            return Ok(start.elapsed());
        }
        Ok(Duration::ZERO)
    }

    /// Empties the file (its records are in a durable snapshot now).
    pub fn clear(&mut self) -> io::Result<()> {
        self.file.set_len(0)?;
        self.file.sync_all()?;
        self.bytes = 0;
        Ok(())
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

/// Reads every intact record of `path` and truncates the file after the last one. A missing
/// file has no records.
pub fn read_log(path: &Path) -> io::Result<LogContents> {
    let mut data = Vec::new();
    match File::open(path) {
        Ok(mut f) => {
            f.read_to_end(&mut data)?;
        }
        Err(e) if e.kind() == io::ErrorKind::NotFound => {
            return Ok(LogContents {
                records: Vec::new(),
                truncated_bytes: 0,
            })
        }
        Err(e) => return Err(e),
    }
    let (records, valid) = parse(&data);
    let truncated_bytes = (data.len() - valid) as u64;
    if truncated_bytes > 0 {
        let file = OpenOptions::new().write(true).open(path)?;
        file.set_len(valid as u64)?;
        file.sync_all()?;
    }
    Ok(LogContents {
        records,
        truncated_bytes,
    })
}

/// The intact records at the start of `data`, and how many bytes they span.
fn parse(data: &[u8]) -> (Vec<Vec<u8>>, usize) {
    let mut records = Vec::new();
    let mut at = 0;
    while data.len() - at >= HEADER {
        let len = u32::from_le_bytes(data[at..at + 4].try_into().expect("4 bytes")) as usize;
        let crc = u32::from_le_bytes(data[at + 4..at + 8].try_into().expect("4 bytes"));
        let start = at + HEADER;
        if len > MAX_RECORD || data.len() - start < len {
            break;
        }
        let payload = &data[start..start + len];
        if crc32fast::hash(payload) != crc {
            break;
        }
        records.push(payload.to_vec());
        at = start + len;
    }
    (records, at)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("factord-log-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir.join("journal.log")
    }

    #[test]
    fn every_torn_tail_is_cut_and_nothing_before_it_is_lost() {
        let path = temp("torn");
        let payloads: Vec<Vec<u8>> = (0..5u8)
            .map(|i| {
                format!(
                    "{{\"record\":{i},\"pad\":\"{}\"}}",
                    "x".repeat(i as usize * 7)
                )
                .into_bytes()
            })
            .collect();
        let mut w = LogWriter::open(&path, Fsync::Always).unwrap();
        let mut ends = Vec::new();
        for p in &payloads {
            w.append(p).unwrap();
            ends.push(w.bytes());
        }
        let whole = std::fs::read(&path).unwrap();
        // Cut the file at every byte: the records that fit whole survive, the rest is dropped.
        for cut in 0..=whole.len() {
            std::fs::write(&path, &whole[..cut]).unwrap();
            let read = read_log(&path).unwrap();
            let complete = ends.iter().filter(|&&e| e as usize <= cut).count();
            assert_eq!(read.records, payloads[..complete], "cut at {cut}");
            let kept = if complete == 0 {
                0
            } else {
                ends[complete - 1] as usize
            };
            assert_eq!(read.truncated_bytes as usize, cut - kept);
            assert_eq!(std::fs::metadata(&path).unwrap().len() as usize, kept);
        }
    }

    #[test]
    fn a_flipped_bit_ends_the_log_at_that_record() {
        let path = temp("flip");
        let mut w = LogWriter::open(&path, Fsync::Never).unwrap();
        for i in 0..4 {
            w.append(format!("record {i}").as_bytes()).unwrap();
        }
        drop(w);
        let mut bytes = std::fs::read(&path).unwrap();
        let third = 2 * (HEADER + 8) + HEADER + 3;
        bytes[third] ^= 0x10;
        std::fs::write(&path, &bytes).unwrap();
        let read = read_log(&path).unwrap();
        assert_eq!(
            read.records,
            vec![b"record 0".to_vec(), b"record 1".to_vec()]
        );
        // Appending after recovery continues a valid log.
        let mut w = LogWriter::open(&path, Fsync::Always).unwrap();
        w.append(b"after").unwrap();
        assert_eq!(read_log(&path).unwrap().records.len(), 3);
        // A header claiming an absurd length is a torn header, not an allocation.
        let mut bytes = std::fs::read(&path).unwrap();
        bytes.extend_from_slice(&u32::MAX.to_le_bytes());
        bytes.extend_from_slice(&[0; 4]);
        std::fs::write(&path, &bytes).unwrap();
        assert_eq!(read_log(&path).unwrap().truncated_bytes, 8);
    }
}
