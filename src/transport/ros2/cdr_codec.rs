//! CDR, as rmw_zenoh carries it: the 4-byte encapsulation header (`00 01 00 00`, CDR little
//! endian, on what we write; either endianness on what we read) then the message, aligned from
//! the end of that header. Encoding and decoding are the `cdr` crate's.

use serde::de::DeserializeOwned;
use serde::Serialize;

/// A payload that is not the CDR of the expected message.
#[derive(Debug, thiserror::Error)]
#[error("not a CDR-encoded {type_name}: {source}")]
pub struct CdrError {
    pub type_name: &'static str,
    #[source]
    pub source: cdr::Error,
}

/// `message` as CDR little endian with its encapsulation header.
pub fn encode<T: Serialize>(message: &T) -> Vec<u8> {
    cdr::serialize::<_, _, cdr::CdrLe>(message, cdr::Infinite)
        .expect("ROS messages of plain structs, strings and sequences always serialise")
}

/// The message of `payload`; reads no further than the payload (a length field beyond it is a
/// truncated message, not an allocation).
pub fn decode<T: DeserializeOwned>(payload: &[u8], type_name: &'static str) -> Result<T, CdrError> {
    cdr::deserialize_from(payload, cdr::Bounded(payload.len() as u64))
        .map_err(|source| CdrError { type_name, source })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transport::ros2::messages::{Header, PoseWithCovarianceStamped, Time};

    #[test]
    fn a_message_round_trips_with_the_little_endian_header() {
        let mut message = PoseWithCovarianceStamped {
            header: Header {
                stamp: Time { sec: 5, nanosec: 7 },
                frame_id: "map".into(),
            },
            ..Default::default()
        };
        message.pose.pose.position.x = 1.5;
        message.pose.covariance.0[35] = 0.25;
        let bytes = encode(&message);
        assert_eq!(&bytes[..4], &[0, 1, 0, 0]);
        // stamp (8), frame_id: length 4 with the NUL, "map\0", then f64s aligned to 8 from
        // the end of the header: 8 + 4 + 4 = 16, already aligned. 7 + 36 f64 follow.
        assert_eq!(bytes.len(), 4 + 16 + 8 * (7 + 36));
        let back: PoseWithCovarianceStamped = decode(&bytes, "x").unwrap();
        assert_eq!(back, message);
    }

    #[test]
    fn truncated_and_garbage_payloads_are_errors() {
        let bytes = encode(&PoseWithCovarianceStamped::default());
        for bad in [&bytes[..bytes.len() - 1], &bytes[..3], &[9, 9, 9, 9, 1][..]] {
            assert!(decode::<PoseWithCovarianceStamped>(bad, "x").is_err());
        }
    }
}
