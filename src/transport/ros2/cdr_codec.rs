//! CDR, as rmw_zenoh carries it: the 4-byte encapsulation header (`00 01 00 00`, CDR little
//! endian, on what we write; either endianness on what we read) then the message, aligned from
//! the end of that header. Encoding and decoding are the `cdr` crate's, but for the strings we
//! read ([`name_string`]).

use std::io::Read;

use serde::de::{DeserializeOwned, Error as _, SeqAccess, Visitor};
use serde::{Deserializer, Serialize};

/// The longest string a message we read may hold, in bytes: ROS frame names are short
/// (`base_link`, `robot1/odom`), and a longer one is not a name.
pub const MAX_NAME_BYTES: usize = 256;

/// A payload that is not the CDR of the expected message: what arrived (its size) and why it
/// does not parse as that type.
#[derive(Debug, thiserror::Error)]
#[error(
    "a {bytes}-byte payload is not a CDR-encoded {type_name}: {}",
    explain(source)
)]
pub struct CdrError {
    pub type_name: &'static str,
    /// The payload's size, header included.
    pub bytes: usize,
    #[source]
    pub source: cdr::Error,
}

/// The cdr crate's reasons in a publisher's terms: its "size limit" is our payload's end, which
/// a shorter message or one of another type reaches first.
fn explain(source: &cdr::Error) -> String {
    let ended = |kind: std::io::ErrorKind| kind == std::io::ErrorKind::UnexpectedEof;
    match source {
        cdr::Error::SizeLimit => TOO_SHORT.into(),
        cdr::Error::Io(e) if ended(e.kind()) => TOO_SHORT.into(),
        other => other.to_string(),
    }
}

const TOO_SHORT: &str =
    "the payload ends before the message does (a message cut short, or one of another type)";

/// `message` as CDR little endian with its encapsulation header.
pub fn encode<T: Serialize>(message: &T) -> Vec<u8> {
    cdr::serialize::<_, _, cdr::CdrLe>(message, cdr::Infinite)
        .expect("ROS messages of plain structs, strings and sequences always serialise")
}

/// The message of `payload` (see [`decode_from`]).
#[cfg(test)]
pub fn decode<T: DeserializeOwned>(payload: &[u8], type_name: &'static str) -> Result<T, CdrError> {
    decode_from(payload, payload.len(), type_name)
}

/// The message read from `payload`, `len` bytes, read as it is decoded (never copied whole);
/// reads no further than `len` bytes (a length field beyond them is a truncated message, not
/// an allocation).
pub fn decode_from<T: DeserializeOwned>(
    payload: impl Read,
    len: usize,
    type_name: &'static str,
) -> Result<T, CdrError> {
    cdr::deserialize_from(payload, cdr::Bounded(len as u64)).map_err(|source| CdrError {
        type_name,
        bytes: len,
        source,
    })
}

/// A CDR string (a u32 length counting the terminating NUL, then the bytes) of at most
/// [`MAX_NAME_BYTES`], refused at its length: the cdr crate's own string reading allocates and
/// zeroes the length it reads before it checks it against the payload (4 GiB for a length of
/// 0xFFFFFFF0). Read as a tuple, CDR's sequence of elements without a length, one byte at a
/// time: never more memory than bytes read. `field` names it in the refusal.
pub fn name_string<'de, D: Deserializer<'de>>(
    deserializer: D,
    field: &'static str,
) -> Result<String, D::Error> {
    struct Name {
        field: &'static str,
    }
    impl<'de> Visitor<'de> for Name {
        type Value = String;
        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            write!(f, "a string of at most {MAX_NAME_BYTES} bytes")
        }
        fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<String, A::Error> {
            let field = self.field;
            let missing = |i| A::Error::invalid_length(i, &self);
            let len: u32 = seq.next_element()?.ok_or_else(|| missing(0))?;
            let len = len as usize;
            if len > MAX_NAME_BYTES + 1 {
                return Err(A::Error::custom(format!(
                    "{field} has a length of {len} bytes: at most {MAX_NAME_BYTES} are taken \
                     (ROS names are short)"
                )));
            }
            let mut bytes = Vec::with_capacity(len);
            for i in 0..len {
                bytes.push(seq.next_element::<u8>()?.ok_or_else(|| missing(i + 1))?);
            }
            if bytes.last() == Some(&0) {
                bytes.pop();
            }
            String::from_utf8(bytes).map_err(|_| A::Error::custom(format!("{field} is not UTF-8")))
        }
    }
    // The length and up to MAX_NAME_BYTES + 1 bytes: the tuple ends where the string does.
    deserializer.deserialize_tuple(MAX_NAME_BYTES + 2, Name { field })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transport::ros2::messages::{Header, Odometry, PoseWithCovarianceStamped, Time};

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

    /// A frame id of `len` bytes ("aaa…") in an otherwise well-formed message.
    fn with_frame_id(len: usize) -> Vec<u8> {
        let mut message = PoseWithCovarianceStamped::default();
        message.header.frame_id = "a".repeat(len);
        encode(&message)
    }

    #[test]
    fn names_are_bounded_at_their_length() {
        let back: PoseWithCovarianceStamped = decode(&with_frame_id(256), "x").unwrap();
        assert_eq!(back.header.frame_id.len(), 256);
        let error = decode::<PoseWithCovarianceStamped>(&with_frame_id(257), "x").unwrap_err();
        assert!(
            error
                .to_string()
                .contains("header.frame_id has a length of 258"),
            "{error}"
        );
        // A length beyond the payload, within the bound, is a message cut short; far beyond it
        // (0xFFFFFFF0) is refused before anything is allocated for it.
        let mut bytes = with_frame_id(3)[..20].to_vec();
        for (len, expected) in [(200u32, "ends before"), (0xFFFF_FFF0, "4294967280 bytes")] {
            bytes[12..16].copy_from_slice(&len.to_le_bytes());
            let error = decode::<PoseWithCovarianceStamped>(&bytes, "x").unwrap_err();
            assert!(error.to_string().contains(expected), "{error}");
        }
    }

    /// A message of another type says what arrived: its size, and that it does not parse as the
    /// expected type (issue 56: "the size limit has been reached" said neither).
    #[test]
    fn a_wrong_type_says_what_arrived() {
        let pose = encode(&PoseWithCovarianceStamped::default());
        let error = decode::<Odometry>(&pose, "nav_msgs/msg/Odometry").unwrap_err();
        let text = error.to_string();
        assert!(
            text.starts_with(&format!(
                "a {}-byte payload is not a CDR-encoded nav_msgs/msg/Odometry",
                pose.len()
            )),
            "{text}"
        );
        assert!(
            text.contains("ends before") && text.contains("another type"),
            "{text}"
        );
        assert!(!text.contains("size limit"), "{text}");
        // Garbage that is not CDR at all: the size again, and the decoder's reason.
        let error = decode::<Odometry>(&[9, 9, 9, 9, 1], "nav_msgs/msg/Odometry").unwrap_err();
        assert!(error.to_string().starts_with("a 5-byte payload"), "{error}");
    }

    #[test]
    fn truncated_and_garbage_payloads_are_errors() {
        let bytes = encode(&PoseWithCovarianceStamped::default());
        for bad in [&bytes[..bytes.len() - 1], &bytes[..3], &[9, 9, 9, 9, 1][..]] {
            assert!(decode::<PoseWithCovarianceStamped>(bad, "x").is_err());
        }
    }
}
