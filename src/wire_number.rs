//! How the wire reads integers, so that the server accepts exactly what the JSON Schemas in
//! `proto/v1/` call an integer.
//!
//! - An integer field also takes a whole-number float (`3.0`, `1e3`): JSON Schema counts those as
//!   integers, and clients that hold every number as a double (JavaScript, numpy) send them so.
//!   Fractions, negative numbers and floats beyond the type's range are refused with the field's
//!   path. From 2^53 on a double no longer tells which integer was meant (`9007199254740993.0`
//!   reads as …992), so floats there are refused too: such ids must be written as integers.
//! - Optional fields take `null` as "absent" (serde's reading; the schemas say so), so this
//!   module keeps that for the optional integers it reads too.

use std::fmt;

use serde::de::{self, Deserializer, Unexpected, Visitor};
use serde::Deserialize;

/// 2^53: from here on neighbouring integers share one double.
const INEXACT_FROM: f64 = 9_007_199_254_740_992.0;

struct WholeNumber;

impl<'de> Visitor<'de> for WholeNumber {
    type Value = u64;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("a non-negative integer (written as a float only below 2^53)")
    }

    fn visit_u64<E: de::Error>(self, v: u64) -> Result<u64, E> {
        Ok(v)
    }

    fn visit_i64<E: de::Error>(self, v: i64) -> Result<u64, E> {
        u64::try_from(v).map_err(|_| E::invalid_value(Unexpected::Signed(v), &self))
    }

    fn visit_f64<E: de::Error>(self, v: f64) -> Result<u64, E> {
        let whole = v.round();
        if (0.0..INEXACT_FROM).contains(&whole) && v == whole {
            Ok(whole as u64)
        } else {
            Err(E::invalid_value(Unexpected::Float(v), &self))
        }
    }
}

/// A `u64` field (keys, ids, milliseconds).
pub fn u64<'de, D: Deserializer<'de>>(deserializer: D) -> Result<u64, D::Error> {
    // Not `deserialize_u64`: inside internally tagged enums serde replays buffered content, and
    // that replay refuses a float for an integer before the visitor sees it.
    deserializer.deserialize_any(WholeNumber)
}

/// A `usize` field (counts).
pub fn usize<'de, D: Deserializer<'de>>(deserializer: D) -> Result<usize, D::Error> {
    let v = u64(deserializer)?;
    usize::try_from(v).map_err(|_| {
        de::Error::invalid_value(Unexpected::Unsigned(v), &"an integer that fits in usize")
    })
}

/// A `u64` read as [`prim@u64`] reads it, as a list element.
#[derive(Deserialize)]
#[serde(transparent)]
pub(crate) struct Whole(#[serde(deserialize_with = "u64")] u64);

impl From<Whole> for u64 {
    fn from(Whole(v): Whole) -> u64 {
        v
    }
}

/// A list of `u64` (keys, factor ids).
pub fn u64_list<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Vec<u64>, D::Error> {
    let list = Vec::<Whole>::deserialize(deserializer)?;
    Ok(list.into_iter().map(|Whole(v)| v).collect())
}

/// An optional `u64`: absent (with `#[serde(default)]`), `null`, or a whole number.
pub fn optional_u64<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Option<u64>, D::Error> {
    Ok(Option::<Whole>::deserialize(deserializer)?.map(|Whole(v)| v))
}

#[cfg(test)]
mod tests {
    use serde::Deserialize;

    #[derive(Debug, Deserialize)]
    struct Fields {
        #[serde(deserialize_with = "super::u64")]
        key: u64,
        #[serde(default, deserialize_with = "super::u64_list")]
        keys: Vec<u64>,
        #[serde(default, deserialize_with = "super::optional_u64")]
        since: Option<u64>,
    }

    fn parse(text: &str) -> Result<Fields, String> {
        serde_json::from_str(text).map_err(|e| e.to_string())
    }

    #[test]
    fn whole_floats_are_integers_and_fractions_are_not() {
        let f = parse(r#"{"key": 3.0, "keys": [1, 2.0, 1e3], "since": 0.0}"#).unwrap();
        assert_eq!((f.key, f.keys, f.since), (3, vec![1, 2, 1000], Some(0)));
        assert_eq!(
            parse(r#"{"key": 2251799813685247.0}"#).unwrap().key,
            2251799813685247
        );
        assert_eq!(
            parse(r#"{"key": 18446744073709551615}"#).unwrap().key,
            u64::MAX
        );
        for bad in [
            "9007199254740993.0",
            "9007199254740992.0",
            "1e19",
            "2.5",
            "-1",
            "-1.0",
            "1e300",
            "18446744073709551616.0",
            "\"3\"",
        ] {
            let err = parse(&format!(r#"{{"key": {bad}}}"#)).unwrap_err();
            assert!(
                err.contains("key") || err.contains("integer"),
                "{bad}: {err}"
            );
        }
        assert!(parse(r#"{"key": 1, "keys": [1, 0.5]}"#).is_err());
        assert!(parse(r#"{"key": 1, "keys": [1, 1000000.001]}"#).is_err());
    }

    #[test]
    fn optional_integers_are_absent_null_or_whole() {
        assert_eq!(parse(r#"{"key": 1}"#).unwrap().since, None);
        assert_eq!(parse(r#"{"key": 1, "since": null}"#).unwrap().since, None);
        assert_eq!(parse(r#"{"key": 1, "since": 4.0}"#).unwrap().since, Some(4));
        assert!(parse(r#"{"key": 1, "since": 4.5}"#).is_err());
    }
}
