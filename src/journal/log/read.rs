//! Reading a record file back (see the parent module for the format): the intact records, a
//! torn tail cut off, or damage reported with the file left as it is.

use std::fs::{File, OpenOptions};
use std::io::{self, Read};
use std::path::Path;

use super::{HEADER, MAX_RECORD};

/// What reading a record file found.
#[derive(Debug)]
pub struct LogContents {
    /// The intact records before the first bad one (all of them when there is none).
    pub records: Vec<Vec<u8>>,
    /// Bytes of a torn tail that were cut off.
    pub truncated_bytes: u64,
    /// A bad record followed by intact ones: the file was left untouched.
    pub corruption: Option<Corruption>,
}

/// Where a record file is damaged: the first bad record, and the first intact record after it
/// (which proves the damage is not a torn tail).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Corruption {
    /// Byte offset of the first record whose length or checksum is wrong.
    pub offset: u64,
    /// Byte offset of the first intact record after it.
    pub next_intact: u64,
    /// Size of the file.
    pub file_bytes: u64,
}

impl std::fmt::Display for Corruption {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "the record at byte {} is damaged (its length or checksum does not match) and intact \
             records follow from byte {} (file size {} bytes): not a torn tail",
            self.offset, self.next_intact, self.file_bytes
        )
    }
}

/// Reads every intact record of `path`. A torn tail (a bad record with nothing intact after it)
/// is cut off; a bad record with intact records after it is reported as [`Corruption`] and the
/// file is not changed. A missing file has no records.
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
                corruption: None,
            })
        }
        Err(e) => return Err(e),
    }
    let (records, valid) = parse(&data);
    // Nothing after the records, or only the zeros the writer grew the file by (see the module
    // doc): kept for the next records.
    if data[valid..].iter().all(|&b| b == 0) {
        return Ok(LogContents {
            records,
            truncated_bytes: 0,
            corruption: None,
        });
    }
    // A bad record: damage when an intact one follows, else a torn tail.
    if let Some(next_intact) = next_intact_record(&data, valid + 1) {
        return Ok(LogContents {
            records,
            truncated_bytes: 0,
            corruption: Some(Corruption {
                offset: valid as u64,
                next_intact: next_intact as u64,
                file_bytes: data.len() as u64,
            }),
        });
    }
    let truncated_bytes = (data.len() - valid) as u64;
    let file = OpenOptions::new().write(true).open(path)?;
    file.set_len(valid as u64)?;
    file.sync_all()?;
    Ok(LogContents {
        records,
        truncated_bytes,
        corruption: None,
    })
}

/// The intact record starting at `at`, if there is one: its payload and where it ends.
fn record_at(data: &[u8], at: usize) -> Option<(&[u8], usize)> {
    let header = data.get(at..at.checked_add(HEADER)?)?;
    let len = u32::from_le_bytes([header[0], header[1], header[2], header[3]]) as usize;
    let crc = u32::from_le_bytes([header[4], header[5], header[6], header[7]]);
    if len > MAX_RECORD {
        return None;
    }
    let start = at + HEADER;
    let payload = data.get(start..start.checked_add(len)?)?;
    (crc32fast::hash(payload) == crc).then_some((payload, start + len))
}

/// The intact records at the start of `data`, and how many bytes they span. An empty record is
/// the zeros after the last one (see the module doc).
fn parse(data: &[u8]) -> (Vec<Vec<u8>>, usize) {
    let mut records = Vec::new();
    let mut at = 0;
    while let Some((payload, end)) = record_at(data, at).filter(|(p, _)| !p.is_empty()) {
        records.push(payload.to_vec());
        at = end;
    }
    (records, at)
}

/// The first offset from `from` on where an intact, non-empty record starts. Empty records are
/// never written, and eight zero bytes (what a file system may leave in a torn tail) would pass
/// as one: the empty payload's CRC is zero. A false match on damaged bytes needs a length that
/// fits and a 32-bit checksum that matches by chance.
fn next_intact_record(data: &[u8], from: usize) -> Option<usize> {
    (from..data.len().saturating_sub(HEADER))
        .find(|&at| record_at(data, at).is_some_and(|(payload, _)| !payload.is_empty()))
}

#[cfg(test)]
mod tests {
    use super::super::tests::temp;
    use super::super::{Fsync, LogWriter};
    use super::*;

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
        // The records, without the zeros the file was grown by.
        let whole = std::fs::read(&path).unwrap()[..w.bytes() as usize].to_vec();
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
    fn a_flipped_bit_with_intact_records_after_it_is_corruption_and_the_file_is_kept() {
        let path = temp("flip");
        let mut w = LogWriter::open(&path, Fsync::Never).unwrap();
        for i in 0..4 {
            w.append(format!("record {i}").as_bytes()).unwrap();
        }
        drop(w);
        let record = HEADER + 8;
        let mut bytes = std::fs::read(&path).unwrap();
        bytes[2 * record + HEADER + 3] ^= 0x10;
        std::fs::write(&path, &bytes).unwrap();
        let read = read_log(&path).unwrap();
        assert_eq!(
            read.records,
            vec![b"record 0".to_vec(), b"record 1".to_vec()]
        );
        assert_eq!(
            read.corruption,
            Some(Corruption {
                offset: 2 * record as u64,
                next_intact: 3 * record as u64,
                file_bytes: bytes.len() as u64,
            })
        );
        assert_eq!(read.truncated_bytes, 0);
        assert_eq!(
            std::fs::read(&path).unwrap(),
            bytes,
            "the file is not changed"
        );
        // A damaged length field is found the same way.
        let mut bytes = std::fs::read(&path).unwrap();
        bytes[2 * record + HEADER + 3] ^= 0x10;
        bytes[record] = 0xff;
        std::fs::write(&path, &bytes).unwrap();
        let read = read_log(&path).unwrap();
        assert_eq!(read.records.len(), 1);
        assert_eq!(
            read.corruption.map(|c| c.next_intact),
            Some(2 * record as u64)
        );
    }

    #[test]
    fn a_flipped_bit_in_the_last_record_is_a_torn_tail() {
        let path = temp("flip-last");
        let mut w = LogWriter::open(&path, Fsync::Never).unwrap();
        for i in 0..4 {
            w.append(format!("record {i}").as_bytes()).unwrap();
        }
        drop(w);
        let mut bytes = std::fs::read(&path).unwrap();
        let third = 3 * (HEADER + 8) + HEADER + 3;
        bytes[third] ^= 0x10;
        // Zeros after it (a file system's torn tail, or the space the file was grown by) are not
        // an intact (empty) record.
        bytes.extend_from_slice(&[0; 24]);
        std::fs::write(&path, &bytes).unwrap();
        let read = read_log(&path).unwrap();
        assert_eq!(read.records.len(), 3);
        assert_eq!(read.corruption, None);
        assert_eq!(
            read.truncated_bytes,
            (bytes.len() - 3 * (HEADER + 8)) as u64
        );
        // Appending after recovery continues a valid log.
        let mut w = LogWriter::open(&path, Fsync::Always).unwrap();
        w.append(b"after").unwrap();
        assert_eq!(read_log(&path).unwrap().records.len(), 4);
        // A header claiming an absurd length is a torn header, not an allocation.
        let mut bytes = std::fs::read(&path).unwrap();
        bytes.truncate(w.bytes() as usize);
        bytes.extend_from_slice(&u32::MAX.to_le_bytes());
        bytes.extend_from_slice(&[0; 4]);
        std::fs::write(&path, &bytes).unwrap();
        assert_eq!(read_log(&path).unwrap().truncated_bytes, 8);
    }

}
