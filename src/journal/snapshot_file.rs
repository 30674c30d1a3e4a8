//! The bytes of `snapshot.json`: the snapshot's JSON inside an envelope that carries its CRC-32,
//!
//! ```text
//! {"crc32":"89abcdef","snapshot":{"sequence":…}}
//! ```
//!
//! written as three pieces around the serialised snapshot (never copied to add the checksum),
//! so the file is still JSON an operator can read (`jq .snapshot`). The checksum covers the
//! bytes between `"snapshot":` and the closing brace exactly as written. A snapshot is renamed
//! into place only once whole and fsynced, so a crash never leaves half of one; a checksum that
//! fails is damage done later (a bad sector, a stray write), which the JSON alone would miss
//! when it changes a digit.
//!
//! A file that does not start with the envelope is a snapshot written before checksums (its
//! bare JSON): it is still read, unverified, so existing state directories load; the next
//! snapshot of that session is written with its checksum. A factord from before checksums reads
//! an enveloped file as a damaged snapshot (no `sequence`): the session is then read-only, its
//! files untouched.
//!
//! Whatever the format, a snapshot at sequence `u64::MAX` is refused: no batch could follow it
//! without a sequence being reused (they would wrap to 0), and no session gets there by
//! accepting batches, so the file was damaged or edited.

use std::path::Path;

use super::{JournalError, Snapshot};

const OPEN: &[u8] = b"{\"crc32\":\"";
const HEX_DIGITS: usize = 8;
const BEFORE_SNAPSHOT: &[u8] = b"\",\"snapshot\":";
pub(super) const CLOSE: &[u8] = b"}";

/// What the file holds before `snapshot` (a serialised [`super::SnapshotOut`]); [`CLOSE`] ends it.
pub(super) fn envelope_head(snapshot: &[u8]) -> Vec<u8> {
    let mut head = OPEN.to_vec();
    head.extend_from_slice(format!("{:08x}", crc32fast::hash(snapshot)).as_bytes());
    head.extend_from_slice(BEFORE_SNAPSHOT);
    head
}

/// Reads the snapshot in `bytes` (the file at `path`), verifying its checksum when it has one.
pub(super) fn decode(path: &Path, bytes: &[u8]) -> Result<Snapshot, JournalError> {
    let json = match bytes.strip_prefix(OPEN) {
        Some(rest) => verified(path, rest)?,
        None => {
            tracing::info!(
                "{}: a snapshot without a checksum (written before snapshots had one): read \
                 unverified; the next snapshot will have one",
                path.display()
            );
            bytes
        }
    };
    let snapshot: Snapshot = serde_json::from_slice(json).map_err(|e| JournalError::Corrupt {
        path: path.into(),
        message: e.to_string(),
    })?;
    if snapshot.sequence == u64::MAX {
        return Err(JournalError::LastSequence { path: path.into() });
    }
    Ok(snapshot)
}

/// The snapshot's JSON in an envelope (`rest` follows its opening), once its checksum matched.
fn verified<'a>(path: &Path, rest: &'a [u8]) -> Result<&'a [u8], JournalError> {
    let malformed = || JournalError::Corrupt {
        path: path.into(),
        message: "the checksum envelope is malformed: expected \
                  {\"crc32\":\"<8 hex digits>\",\"snapshot\":<the snapshot>}"
            .into(),
    };
    let hex = rest.get(..HEX_DIGITS).ok_or_else(malformed)?;
    let recorded = std::str::from_utf8(hex)
        .ok()
        .filter(|h| h.bytes().all(|b| b.is_ascii_hexdigit()))
        .and_then(|h| u32::from_str_radix(h, 16).ok())
        .ok_or_else(malformed)?;
    let json = rest[HEX_DIGITS..]
        .strip_prefix(BEFORE_SNAPSHOT)
        .and_then(|r| r.strip_suffix(CLOSE))
        .ok_or_else(malformed)?;
    let computed = crc32fast::hash(json);
    if computed != recorded {
        return Err(JournalError::SnapshotChecksum {
            path: path.into(),
            recorded,
            computed,
        });
    }
    Ok(json)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn snapshot(sequence: u64) -> Vec<u8> {
        serde_json::to_vec(
            &serde_json::json!({"sequence": sequence, "next_factor_id": 3,
            "auto_optimize": {"policy": "manual"}, "variables": [], "factors": []}),
        )
        .unwrap()
    }

    fn file(snapshot: &[u8]) -> Vec<u8> {
        [&envelope_head(snapshot), snapshot, CLOSE].concat()
    }

    #[test]
    fn an_enveloped_snapshot_reads_back_and_is_still_json() {
        let bytes = file(&snapshot(12));
        let read = decode(Path::new("s.json"), &bytes).unwrap();
        assert_eq!((read.sequence, read.next_factor_id), (12, 3));
        let json: serde_json::Value = serde_json::from_slice(&bytes).unwrap();
        assert_eq!(json["snapshot"]["sequence"], 12);
        assert_eq!(json["crc32"].as_str().map(str::len), Some(8));
    }

    #[test]
    fn a_changed_digit_fails_the_checksum() {
        let mut bytes = file(&snapshot(12));
        let at = bytes.windows(2).position(|w| w == b"12").unwrap();
        bytes[at] = b'3';
        let e = decode(Path::new("s.json"), &bytes).unwrap_err();
        assert!(matches!(e, JournalError::SnapshotChecksum { .. }), "{e}");
        assert!(
            e.to_string().starts_with("s.json: checksum mismatch"),
            "{e}"
        );
    }

    #[test]
    fn a_snapshot_without_a_checksum_is_still_read() {
        let read = decode(Path::new("s.json"), &snapshot(7)).unwrap();
        assert_eq!(read.sequence, 7);
    }

    #[test]
    fn a_malformed_envelope_is_corrupt() {
        let good = file(&snapshot(1));
        let cases = [
            good[..12].to_vec(),
            [&good[..good.len() - 1], b" "].concat(),
            [OPEN, b"zzzzzzzz", &good[OPEN.len() + HEX_DIGITS..]].concat(),
            [OPEN, b"+1234567", &good[OPEN.len() + HEX_DIGITS..]].concat(),
        ];
        for bytes in cases {
            let e = decode(Path::new("s.json"), &bytes).unwrap_err();
            assert!(e.to_string().contains("envelope is malformed"), "{e}");
        }
    }

    #[test]
    fn the_last_sequence_is_refused_with_or_without_a_checksum() {
        for bytes in [file(&snapshot(u64::MAX)), snapshot(u64::MAX)] {
            let e = decode(Path::new("s.json"), &bytes).unwrap_err();
            assert!(matches!(e, JournalError::LastSequence { .. }), "{e}");
            assert!(e.to_string().contains("18446744073709551615"), "{e}");
        }
        assert_eq!(
            decode(Path::new("s.json"), &file(&snapshot(u64::MAX - 1)))
                .unwrap()
                .sequence,
            u64::MAX - 1
        );
    }
}
