//! The binary form of an `estimate` event, published on zenoh beside the JSON one
//! (`<p>/<session>/bin/poses`, see `crate::transport::zenoh`) for clients that receive many
//! poses: about 40 bytes per SE(2) pose against about 100 in JSON, and no number formatting or
//! parsing at either end. The layout is specified in `proto/v1/poses-binary.md`; this module is
//! its one encoder and a decoder for tests, benchmarks and Rust clients.
//!
//! All integers and floats are little-endian, with no padding:
//!
//! ```text
//! header   magic "FDPB" (4 bytes) | version u32 = 1 | sequence u64 | groups u32
//! group    kind length u8 | kind (ASCII) | dimension u8 | count u32
//!          then count records: key u64 | changed u64 | value f64 × dimension
//! ```
//!
//! A group is a run of consecutive variables of one kind, in the estimate's order (ascending
//! key), so a stream of poses is one group however long; poses interleaved with landmarks make
//! several. The values are the wire encoding of the JSON form (se2 `[x, y, θ]`, se3
//! `[x, y, z, qx, qy, qz, qw]`, …); the variables' stamps are left out (the JSON topic and the
//! estimate route carry them).

use std::borrow::Cow;

use super::wire::{Estimate, VariableValue};

/// The first four bytes of every binary estimate (a JSON event starts with `{`).
pub const MAGIC: &[u8; 4] = b"FDPB";
/// The layout's version; a change to it is a new version, never a change of this one.
pub const VERSION: u32 = 1;

const HEADER_BYTES: usize = 4 + 4 + 8 + 4;

/// Why bytes are not a binary estimate.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PosesBinaryError {
    #[error("not a binary estimate: it does not start with \"FDPB\"")]
    Magic,
    #[error("binary estimate version {0} is not known (this build reads version 1)")]
    Version(u32),
    #[error("binary estimate cut short at byte {at}: {what} needs {needed} more bytes")]
    Truncated {
        at: usize,
        what: &'static str,
        needed: usize,
    },
    #[error("binary estimate: group {group} names a kind that is not ASCII")]
    Kind { group: usize },
    #[error("binary estimate: {0} bytes after the last group")]
    Trailing(usize),
}

/// `estimate` in the binary layout (the session's name is not in it: the key names it).
pub fn encode(estimate: &Estimate) -> Vec<u8> {
    let values: usize = estimate.variables.iter().map(|v| v.value.len()).sum();
    let mut out = Vec::with_capacity(HEADER_BYTES + 16 * estimate.variables.len() + 8 * values);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&VERSION.to_le_bytes());
    out.extend_from_slice(&estimate.sequence.to_le_bytes());
    let groups_at = out.len();
    out.extend_from_slice(&0u32.to_le_bytes());
    let mut groups = 0u32;
    for run in estimate.variables.chunk_by(same_group) {
        // A kind name or a dimension beyond a byte does not occur (the catalogue's longest name
        // is short, its largest variable 9 numbers); split such a run rather than corrupt it.
        let kind = &run[0].kind.as_bytes()[..run[0].kind.len().min(u8::MAX as usize)];
        let dimension = run[0].value.len().min(u8::MAX as usize);
        for records in run.chunks(u32::MAX as usize) {
            out.push(kind.len() as u8);
            out.extend_from_slice(kind);
            out.push(dimension as u8);
            out.extend_from_slice(&(records.len() as u32).to_le_bytes());
            for v in records {
                out.extend_from_slice(&v.key.to_le_bytes());
                out.extend_from_slice(&v.changed.to_le_bytes());
                for x in &v.value[..dimension] {
                    out.extend_from_slice(&x.to_le_bytes());
                }
            }
            groups += 1;
        }
    }
    out[groups_at..groups_at + 4].copy_from_slice(&groups.to_le_bytes());
    out
}

fn same_group(a: &VariableValue, b: &VariableValue) -> bool {
    a.kind == b.kind && a.value.len() == b.value.len()
}

/// Reads a binary estimate back (`session` is the one its key names); stamps are `None`.
pub fn decode(bytes: &[u8], session: &str) -> Result<Estimate, PosesBinaryError> {
    let mut r = Reader { bytes, at: 0 };
    if r.take(4, "the magic")
        .map_err(|_| PosesBinaryError::Magic)?
        != MAGIC
    {
        return Err(PosesBinaryError::Magic);
    }
    let version = r.u32("the version")?;
    if version != VERSION {
        return Err(PosesBinaryError::Version(version));
    }
    let sequence = r.u64("the sequence")?;
    let groups = r.u32("the number of groups")? as usize;
    let mut variables = Vec::new();
    for group in 0..groups {
        let length = r.take(1, "a kind's length")?[0] as usize;
        let kind = std::str::from_utf8(r.take(length, "a kind")?)
            .ok()
            .filter(|k| k.is_ascii())
            .ok_or(PosesBinaryError::Kind { group })?;
        let kind: Cow<'static, str> = Cow::Owned(kind.to_owned());
        let dimension = r.take(1, "a dimension")?[0] as usize;
        let count = r.u32("a group's count")? as usize;
        // Checked before reserving, so a forged count cannot make the reader allocate.
        r.ensure(
            count.saturating_mul(16 + 8 * dimension),
            "a group's records",
        )?;
        variables.reserve(count);
        for _ in 0..count {
            let key = r.u64("a key")?;
            let changed = r.u64("a change sequence")?;
            let value = (0..dimension)
                .map(|_| r.u64("a value").map(f64::from_bits))
                .collect::<Result<_, _>>()?;
            variables.push(VariableValue {
                key,
                kind: kind.clone(),
                value,
                changed,
                stamp: None,
            });
        }
    }
    match bytes.len() - r.at {
        0 => Ok(Estimate {
            session: session.to_owned(),
            sequence,
            variables,
        }),
        n => Err(PosesBinaryError::Trailing(n)),
    }
}

struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn ensure(&self, n: usize, what: &'static str) -> Result<(), PosesBinaryError> {
        let left = self.bytes.len() - self.at;
        match n <= left {
            true => Ok(()),
            false => Err(PosesBinaryError::Truncated {
                at: self.at,
                what,
                needed: n - left,
            }),
        }
    }

    fn take(&mut self, n: usize, what: &'static str) -> Result<&'a [u8], PosesBinaryError> {
        self.ensure(n, what)?;
        let out = &self.bytes[self.at..self.at + n];
        self.at += n;
        Ok(out)
    }

    fn u32(&mut self, what: &'static str) -> Result<u32, PosesBinaryError> {
        let b = self.take(4, what)?;
        Ok(u32::from_le_bytes(b.try_into().expect("took 4 bytes")))
    }

    fn u64(&mut self, what: &'static str) -> Result<u64, PosesBinaryError> {
        let b = self.take(8, what)?;
        Ok(u64::from_le_bytes(b.try_into().expect("took 8 bytes")))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn variable(key: u64, kind: &'static str, value: &[f64], changed: u64) -> VariableValue {
        VariableValue {
            key,
            kind: kind.into(),
            value: value.into(),
            changed,
            stamp: None,
        }
    }

    fn mixed() -> Estimate {
        Estimate {
            session: "s".into(),
            sequence: 42,
            variables: vec![
                variable(0, "se2", &[1.0, -2.5, 0.25], 3),
                variable(1, "se2", &[f64::MIN_POSITIVE, 1e300, -0.0], 42),
                variable(7, "point2", &[4.0, 5.0], 41),
                variable(9, "se2", &[0.0, 0.0, std::f64::consts::PI], 40),
            ],
        }
    }

    #[test]
    fn every_value_comes_back_bit_for_bit_in_order() {
        let estimate = mixed();
        let bytes = encode(&estimate);
        let back = decode(&bytes, "s").unwrap();
        assert_eq!(back.sequence, 42);
        assert_eq!(back.variables.len(), 4);
        for (a, b) in back.variables.iter().zip(&estimate.variables) {
            assert_eq!((a.key, &a.kind, a.changed), (b.key, &b.kind, b.changed));
            let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&a.value), bits(&b.value));
        }
    }

    #[test]
    fn the_layout_is_the_documented_one() {
        let bytes = encode(&mixed());
        assert_eq!(&bytes[..4], b"FDPB");
        assert_eq!(u32::from_le_bytes(bytes[4..8].try_into().unwrap()), 1);
        assert_eq!(u64::from_le_bytes(bytes[8..16].try_into().unwrap()), 42);
        // se2 ×2, point2, se2: three runs.
        assert_eq!(u32::from_le_bytes(bytes[16..20].try_into().unwrap()), 3);
        assert_eq!(&bytes[20..24], b"\x03se2");
        assert_eq!(bytes[24], 3);
        assert_eq!(u32::from_le_bytes(bytes[25..29].try_into().unwrap()), 2);
        assert_eq!(u64::from_le_bytes(bytes[29..37].try_into().unwrap()), 0);
        assert_eq!(u64::from_le_bytes(bytes[37..45].try_into().unwrap()), 3);
        assert_eq!(f64::from_le_bytes(bytes[45..53].try_into().unwrap()), 1.0);
        let group = |kind: usize, dim: usize, n: usize| 1 + kind + 1 + 4 + n * (16 + 8 * dim);
        assert_eq!(
            bytes.len(),
            HEADER_BYTES + group(3, 3, 2) + group(6, 2, 1) + group(3, 3, 1)
        );
    }

    #[test]
    fn an_empty_estimate_is_a_header() {
        let empty = Estimate {
            session: "s".into(),
            sequence: 5,
            variables: vec![],
        };
        let bytes = encode(&empty);
        assert_eq!(bytes.len(), HEADER_BYTES);
        assert!(decode(&bytes, "s").unwrap().variables.is_empty());
    }

    #[test]
    fn damaged_bytes_are_refused_with_where_and_what() {
        let bytes = encode(&mixed());
        assert_eq!(
            decode(b"{\"type\":", "s").unwrap_err(),
            PosesBinaryError::Magic
        );
        assert_eq!(decode(b"FD", "s").unwrap_err(), PosesBinaryError::Magic);
        let mut newer = bytes.clone();
        newer[4] = 2;
        assert_eq!(
            decode(&newer, "s").unwrap_err(),
            PosesBinaryError::Version(2)
        );
        for cut in [10, 20, 24, 30, bytes.len() - 1] {
            let err = decode(&bytes[..cut], "s").unwrap_err();
            assert!(
                matches!(err, PosesBinaryError::Truncated { .. }),
                "{cut}: {err}"
            );
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert_eq!(
            decode(&longer, "s").unwrap_err(),
            PosesBinaryError::Trailing(1)
        );
        // A forged count larger than the bytes: refused before anything is reserved.
        let mut forged = bytes.clone();
        forged[25..29].copy_from_slice(&u32::MAX.to_le_bytes());
        let err = decode(&forged, "s").unwrap_err();
        assert!(matches!(
            err,
            PosesBinaryError::Truncated {
                what: "a group's records",
                ..
            }
        ));
        let mut not_ascii = bytes;
        not_ascii[21] = 0xff;
        assert_eq!(
            decode(&not_ascii, "s").unwrap_err(),
            PosesBinaryError::Kind { group: 0 }
        );
    }
}
