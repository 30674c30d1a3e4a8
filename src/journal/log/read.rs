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

/// The smallest unit a disk writes whole or not at all. A crash leaves each sector of an append
/// written or as it was (zeros: records are written into zeros or past the file's end, see the
/// parent module); a larger sector is whole pieces of this size.
const SECTOR: usize = 512;

/// Where a record file is damaged, and why that is not a torn tail.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Corruption {
    /// Byte offset of the first record whose length or checksum is wrong.
    pub offset: u64,
    pub evidence: Evidence,
    /// Size of the file.
    pub file_bytes: u64,
}

/// What proves a bad record was damaged after it was written, not torn by a crash.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Evidence {
    /// An intact record starts at this offset after it: an append only ever tears the last one.
    IntactAfter(u64),
    /// It is the last record but was written whole: its length fits the file, no sector's share
    /// of its payload reads as zeros and neither does its last byte (see [`written_whole`]). Its
    /// checksum fails because its bytes changed later; under `fsync always` it was
    /// acknowledged.
    WrittenWhole { payload_bytes: u64 },
}

impl std::fmt::Display for Corruption {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (offset, size) = (self.offset, self.file_bytes);
        match self.evidence {
            Evidence::IntactAfter(next) => write!(
                f,
                "the record at byte {offset} is damaged (its length or checksum does not match) \
                 and intact records follow from byte {next} (file size {size} bytes): not a torn \
                 tail"
            ),
            Evidence::WrittenWhole { payload_bytes } => write!(
                f,
                "the last record, at byte {offset}, is damaged: its checksum does not match, yet \
                 all of its {payload_bytes} bytes were written (its length fits the file, none of \
                 its sectors reads as zeros; file size {size} bytes): not a torn tail, and it may \
                 have been acknowledged"
            ),
        }
    }
}

/// Reads every intact record of `path`. A torn tail (a bad last record that a crash could have
/// left) is cut off; a bad record that is damage ([`Evidence`]) is reported as [`Corruption`] and
/// the file is not changed. A missing file has no records.
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
    // A bad record: damage when something proves it, else a torn tail.
    if let Some(evidence) = damage_evidence(&data, valid) {
        return Ok(LogContents {
            records,
            truncated_bytes: 0,
            corruption: Some(Corruption {
                offset: valid as u64,
                evidence,
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

/// Why the bad record at `at` is damage, not a torn tail; `None` when a crash could have left it.
fn damage_evidence(data: &[u8], at: usize) -> Option<Evidence> {
    if let Some(next) = next_intact_record(data, at + 1) {
        return Some(Evidence::IntactAfter(next as u64));
    }
    written_whole(data, at).map(|payload_bytes| Evidence::WrittenWhole { payload_bytes })
}

/// The payload length of the record at `at` when all of it was written: its length fits the
/// file, its last byte is not zero (a write cut short leaves zeros after what it wrote), and no
/// sector's share of it is all zeros (a crash may write an append's sectors in any order). A
/// payload is JSON, which has no zero byte. A flipped byte in the last record passes; a record
/// torn in the zeros the file was grown by does not.
fn written_whole(data: &[u8], at: usize) -> Option<u64> {
    let header = data.get(at..at.checked_add(HEADER)?)?;
    let len = u32::from_le_bytes([header[0], header[1], header[2], header[3]]) as usize;
    if len == 0 || len > MAX_RECORD {
        return None;
    }
    let start = at + HEADER;
    let payload = data.get(start..start.checked_add(len)?)?;
    let blank = |piece: &[u8]| piece.iter().all(|&b| b == 0);
    let (first, rest) = payload.split_at((SECTOR - start % SECTOR).min(len));
    let whole = payload.last() != Some(&0) && !blank(first) && !rest.chunks(SECTOR).any(blank);
    whole.then_some(len as u64)
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
                evidence: Evidence::IntactAfter(3 * record as u64),
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
            read.corruption.map(|c| c.evidence),
            Some(Evidence::IntactAfter(2 * record as u64))
        );
    }

    /// Item 9 of issue 52: the last record, acknowledged under `fsync always`, damaged later.
    #[test]
    fn a_flipped_bit_in_the_last_record_is_damage_and_the_file_is_kept() {
        let path = temp("flip-last");
        let mut w = LogWriter::open(&path, Fsync::Never).unwrap();
        for i in 0..4 {
            w.append(format!("record {i}").as_bytes()).unwrap();
        }
        drop(w);
        let last = 3 * (HEADER + 8);
        let whole = std::fs::read(&path).unwrap();
        // A bit of its payload, of its checksum field.
        for (at, bit) in [(last + HEADER + 3, 0x10), (last + 5, 0x01)] {
            let mut bytes = whole.clone();
            bytes[at] ^= bit;
            std::fs::write(&path, &bytes).unwrap();
            let read = read_log(&path).unwrap();
            assert_eq!(read.records.len(), 3, "byte {at}");
            let payload_bytes = u32::from_le_bytes(bytes[last..last + 4].try_into().unwrap());
            assert_eq!(
                read.corruption,
                Some(Corruption {
                    offset: last as u64,
                    evidence: Evidence::WrittenWhole {
                        payload_bytes: payload_bytes.into()
                    },
                    file_bytes: bytes.len() as u64,
                }),
                "byte {at}"
            );
            assert_eq!(read.truncated_bytes, 0);
            assert_eq!(std::fs::read(&path).unwrap(), bytes, "the file is kept");
        }
    }

    /// What a crash can leave of the last append (its unwritten bytes read as zeros, or are past
    /// the file's end) is a torn tail: cut, and appending goes on after the records before it.
    #[test]
    fn a_last_record_a_crash_could_have_torn_is_cut() {
        let path = temp("torn-last");
        let payload = |i: u8| format!("{{\"record\":{i},\"pad\":\"{}\"}}", "x".repeat(1500));
        let mut w = LogWriter::open(&path, Fsync::Never).unwrap();
        w.append(payload(0).as_bytes()).unwrap();
        let last = w.bytes() as usize;
        w.append(payload(1).as_bytes()).unwrap();
        let end = w.bytes() as usize;
        drop(w);
        let whole = std::fs::read(&path).unwrap();
        let sector = (last + HEADER + 600) / SECTOR * SECTOR;
        let absurd = |b: &mut Vec<u8>| b[last..last + 4].copy_from_slice(&u32::MAX.to_le_bytes());
        type Damage<'a> = &'a dyn Fn(&mut Vec<u8>);
        let cases: [(&str, Damage); 4] = [
            ("a write cut short", &|b| b[end - 100..end].fill(0)),
            ("a sector not written", &|b| {
                b[sector..sector + SECTOR].fill(0)
            }),
            ("its end past the file's", &|b| b.truncate(end - 10)),
            ("an absurd length", &absurd),
        ];
        for (what, damage) in cases {
            let mut bytes = whole.clone();
            damage(&mut bytes);
            std::fs::write(&path, &bytes).unwrap();
            let read = read_log(&path).unwrap();
            assert_eq!(read.records, [payload(0).into_bytes()], "{what}");
            assert_eq!(read.corruption, None, "{what}");
            assert_eq!(read.truncated_bytes, (bytes.len() - last) as u64, "{what}");
            let mut w = LogWriter::open(&path, Fsync::Always).unwrap();
            w.append(b"after").unwrap();
            assert_eq!(read_log(&path).unwrap().records.len(), 2, "{what}");
        }
    }
}
