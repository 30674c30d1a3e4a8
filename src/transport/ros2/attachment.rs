//! The attachment rmw_zenoh puts on every sample: sequence number, source timestamp and the
//! publisher's GID, serialised with zenoh-ext's serializer (`AttachmentData::serialize_to_zbytes`
//! in rmw_zenoh_cpp, Jazzy 0.2 and later, Kilted, Rolling):
//!
//! ```text
//! offset 0   i64 LE   sequence number (per publisher, from 1)
//! offset 8   i64 LE   source timestamp, ns since the UNIX epoch
//! offset 16  0x10     the GID's length (LEB128: a std::array is a sequence for zenoh-ext)
//! offset 17  16 bytes the GID
//! ```
//!
//! Written out here rather than through `zenoh-ext` (33 fixed bytes; the Python test reads
//! and writes them with eclipse-zenoh's `zenoh.ext` serializer, which checks this layout).

/// `RMW_GID_STORAGE_SIZE` since Iron.
pub const GID_SIZE: usize = 16;

pub const ENCODED_SIZE: usize = 8 + 8 + 1 + GID_SIZE;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Attachment {
    pub sequence_number: i64,
    pub source_timestamp_ns: i64,
    pub source_gid: [u8; GID_SIZE],
}

#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("not an rmw_zenoh attachment: {len} bytes, expected {ENCODED_SIZE} with a GID length of {GID_SIZE}")]
pub struct AttachmentError {
    pub len: usize,
}

impl Attachment {
    /// Sample `sequence_number` of `source_gid`, stamped now (wall clock, ns since the epoch).
    pub fn stamped_now(sequence_number: i64, source_gid: [u8; GID_SIZE]) -> Self {
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as i64);
        Self {
            sequence_number,
            source_timestamp_ns: now,
            source_gid,
        }
    }

    pub fn encode(&self) -> [u8; ENCODED_SIZE] {
        let mut bytes = [0u8; ENCODED_SIZE];
        bytes[..8].copy_from_slice(&self.sequence_number.to_le_bytes());
        bytes[8..16].copy_from_slice(&self.source_timestamp_ns.to_le_bytes());
        bytes[16] = GID_SIZE as u8;
        bytes[17..].copy_from_slice(&self.source_gid);
        bytes
    }

    pub fn decode(bytes: &[u8]) -> Result<Self, AttachmentError> {
        let error = AttachmentError { len: bytes.len() };
        if bytes.len() != ENCODED_SIZE || usize::from(bytes[16]) != GID_SIZE {
            return Err(error);
        }
        let int = |range: std::ops::Range<usize>| {
            i64::from_le_bytes(bytes[range].try_into().expect("8 bytes"))
        };
        Ok(Self {
            sequence_number: int(0..8),
            source_timestamp_ns: int(8..16),
            source_gid: bytes[17..].try_into().expect("16 bytes"),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_layout_is_rmw_zenohs() {
        let a = Attachment {
            sequence_number: 1,
            source_timestamp_ns: 0x0102_0304_0506_0708,
            source_gid: [0xab; GID_SIZE],
        };
        let bytes = a.encode();
        assert_eq!(&bytes[..9], &[1, 0, 0, 0, 0, 0, 0, 0, 8]);
        assert_eq!(bytes[16], 16);
        assert_eq!(Attachment::decode(&bytes), Ok(a));
        assert!(Attachment::decode(&bytes[..32]).is_err());
    }
}
