//! How the wire reads lists, so that an oversized request is refused while it is decoded, before
//! it costs memory.
//!
//! A request body is bounded in bytes, but its decoded form is not: `[1,1,1,…]` is two bytes an
//! element on the wire and eight (sixteen while a `Vec` doubles) once decoded. So:
//! - the lists that hold a request's *items* (a batch's variables, factors, removals, fixes,
//!   guesses; a fusion batch's messages) draw on one budget per decoding, set by
//!   [`decode_within`] from `limits.max_batch_items`. The element past the budget stops the
//!   decoding, and [`decode_within`] reports [`ItemsExceeded`];
//! - the number lists inside an item (values, measurements, information matrices) are at most
//!   [`MAX_NUMBERS`] long: no variable or factor kind has more.

use std::cell::Cell;
use std::fmt;
use std::marker::PhantomData;

use serde::de::{self, Deserializer, SeqAccess, Visitor};
use serde::Deserialize;

/// The longest number list any variable or factor takes (a 15×15 information matrix is 225;
/// photometric patches and BA cameras are shorter).
pub const MAX_NUMBERS: usize = 1024;

thread_local! {
    /// Items the decoding on this thread may still take (`None`: not bounded).
    static ITEMS_LEFT: Cell<Option<usize>> = const { Cell::new(None) };
    /// Whether the decoding on this thread ran out of items.
    static EXCEEDED: Cell<bool> = const { Cell::new(false) };
}

/// The request had more items than the budget given to [`decode_within`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("the request has more than {limit} items")]
pub struct ItemsExceeded {
    pub limit: usize,
}

/// Runs `decode` (a serde decoding on this thread) with at most `max_items` items in the lists
/// that hold items. `Err(ItemsExceeded)` when it ran out, whatever `decode` then returned.
pub fn decode_within<T>(max_items: usize, decode: impl FnOnce() -> T) -> Result<T, ItemsExceeded> {
    let outer = ITEMS_LEFT.with(|left| left.replace(Some(max_items)));
    EXCEEDED.with(|e| e.set(false));
    let decoded = decode();
    ITEMS_LEFT.with(|left| left.set(outer));
    match EXCEEDED.with(|e| e.replace(false)) {
        true => Err(ItemsExceeded { limit: max_items }),
        false => Ok(decoded),
    }
}

fn take_item<E: de::Error>() -> Result<(), E> {
    ITEMS_LEFT.with(|left| match left.get() {
        None => Ok(()),
        Some(0) => {
            EXCEEDED.with(|e| e.set(true));
            Err(E::custom("more items than limits.max_batch_items"))
        }
        Some(n) => {
            left.set(Some(n - 1));
            Ok(())
        }
    })
}

/// A list read element by element, each element decoded as `W` and kept as `T`, and counted.
struct Bounded<W, T> {
    /// Counts against the item budget (else: at most [`MAX_NUMBERS`]).
    items: bool,
    kept: PhantomData<fn(W) -> T>,
}

impl<'de, W: Deserialize<'de> + Into<T>, T> Visitor<'de> for Bounded<W, T> {
    type Value = Vec<T>;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        match self.items {
            true => f.write_str("a list"),
            false => write!(f, "a list of at most {MAX_NUMBERS} numbers"),
        }
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Vec<T>, A::Error> {
        let mut list = Vec::new();
        // Each element is small (number lists inside it are bounded too): decode it, then
        // count it before keeping it.
        while let Some(element) = seq.next_element::<W>()? {
            if self.items {
                take_item::<A::Error>()?;
            } else if list.len() == MAX_NUMBERS {
                return Err(de::Error::invalid_length(MAX_NUMBERS + 1, &self));
            }
            list.push(element.into());
        }
        Ok(list)
    }
}

fn bounded<'de, D, W, T>(deserializer: D, items: bool) -> Result<Vec<T>, D::Error>
where
    D: Deserializer<'de>,
    W: Deserialize<'de> + Into<T>,
{
    let visitor = Bounded::<W, T> {
        items,
        kept: PhantomData,
    };
    deserializer.deserialize_seq(visitor)
}

/// A list of a request's items (variables, factors, guesses, messages).
pub fn items<'de, D, T>(deserializer: D) -> Result<Vec<T>, D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    bounded::<D, T, T>(deserializer, true)
}

/// A list of items that are keys or factor ids (removals, fixes), read as
/// [`super::wire_number::u64`] reads one.
pub fn key_items<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Vec<u64>, D::Error> {
    bounded::<D, super::wire_number::Whole, u64>(deserializer, true)
}

/// A factor's keys: at most [`MAX_NUMBERS`], each read as [`super::wire_number::u64`] reads one.
pub fn keys<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Vec<u64>, D::Error> {
    bounded::<D, super::wire_number::Whole, u64>(deserializer, false)
}

/// A list of at most [`MAX_NUMBERS`] numbers.
pub fn numbers<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Vec<f64>, D::Error> {
    bounded::<D, f64, f64>(deserializer, false)
}

/// An optional list of at most [`MAX_NUMBERS`] numbers (`null` is absent).
pub fn optional_numbers<'de, D: Deserializer<'de>>(
    deserializer: D,
) -> Result<Option<Vec<f64>>, D::Error> {
    #[derive(Deserialize)]
    struct Numbers(#[serde(deserialize_with = "numbers")] Vec<f64>);
    Ok(Option::<Numbers>::deserialize(deserializer)?.map(|Numbers(v)| v))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, Deserialize)]
    struct Request {
        #[serde(default, deserialize_with = "items")]
        things: Vec<serde_json::Value>,
        #[serde(default, deserialize_with = "key_items")]
        keys: Vec<u64>,
        #[serde(default, deserialize_with = "optional_numbers")]
        value: Option<Vec<f64>>,
    }

    fn decode(text: &str, max: usize) -> Result<Result<Request, String>, ItemsExceeded> {
        decode_within(max, || {
            serde_json::from_str::<Request>(text).map_err(|e| e.to_string())
        })
    }

    #[test]
    fn items_are_counted_across_lists_up_to_the_limit() {
        let r = decode(r#"{"things": [1, 2], "keys": [3.0, 4]}"#, 4)
            .unwrap()
            .unwrap();
        assert_eq!((r.things.len(), r.keys), (2, vec![3, 4]));
        assert_eq!(
            decode(r#"{"things": [1, 2], "keys": [3, 4, 5]}"#, 4).unwrap_err(),
            ItemsExceeded { limit: 4 }
        );
        assert!(decode(r#"{"things": []}"#, 0).unwrap().is_ok());
        // Unbounded outside decode_within.
        let many = format!("{{\"keys\": [{}]}}", vec!["1"; 5000].join(","));
        assert!(serde_json::from_str::<Request>(&many).is_ok());
    }

    #[test]
    fn number_lists_stop_past_their_maximum() {
        let at = |n: usize| format!("{{\"value\": [{}]}}", vec!["0.5"; n].join(","));
        let ok = decode(&at(MAX_NUMBERS), 10).unwrap().unwrap();
        assert_eq!(ok.value.unwrap().len(), MAX_NUMBERS);
        let refused = decode(&at(MAX_NUMBERS + 1), 10).unwrap().unwrap_err();
        assert!(refused.contains("at most 1024 numbers"), "{refused}");
        assert!(decode(r#"{"value": null}"#, 1)
            .unwrap()
            .unwrap()
            .value
            .is_none());
    }
}
