//! How the wire reads lists, so that an oversized request is refused while it is decoded, before
//! it costs memory.
//!
//! A request body is bounded in bytes, but its decoded form is not: `[1,1,1,…]` is two bytes an
//! element on the wire and eight (sixteen while a `Vec` doubles) once decoded. So:
//! - the lists that hold a request's *items* (a batch's variables, factors, removals, fixes,
//!   guesses; a fusion batch's messages) draw on one budget per decoding, set by
//!   [`decode_within`] from `limits.max_batch_items`. The element past the budget stops the
//!   decoding, and [`decode_within`] reports [`ItemsExceeded`];
//! - before any of that, [`check_shape`] bounds every list in the text in one pass over its
//!   bytes: item lists by the same limit, the lists inside an item (values, measurements,
//!   information matrices) by [`MAX_NUMBERS`]: no variable or factor kind has more.

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

/// A list of items read element by element, each decoded as `W`, kept as `T` and counted.
struct Items<W, T>(PhantomData<fn(W) -> T>);

impl<'de, W: Deserialize<'de> + Into<T>, T> Visitor<'de> for Items<W, T> {
    type Value = Vec<T>;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("a list")
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Vec<T>, A::Error> {
        let mut list = Vec::new();
        // Each element is small (the shape check bounds the lists inside it): decode it, then
        // count it before keeping it.
        while let Some(element) = seq.next_element::<W>()? {
            take_item::<A::Error>()?;
            list.push(element.into());
        }
        Ok(list)
    }
}

/// A list of a request's items (variables, factors, guesses, messages).
pub fn items<'de, D, T>(deserializer: D) -> Result<Vec<T>, D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    deserializer.deserialize_seq(Items::<T, T>(PhantomData))
}

/// A list of items that are keys or factor ids (removals, fixes), each read as
/// [`crate::wire_number::u64`] reads one.
pub fn key_items<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Vec<u64>, D::Error> {
    deserializer.deserialize_seq(Items::<crate::wire_number::Whole, u64>(PhantomData))
}

/// A list in a JSON text longer than its place allows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum ShapeError {
    #[error("a list of the request has more than {limit} elements (limits.max_batch_items)")]
    TooManyItems { limit: usize },
    #[error("a list inside an item has more than {MAX_NUMBERS} elements")]
    TooManyNumbers,
}

/// Checks the lists of a JSON text before it is parsed, in one pass over its bytes: lists that
/// are not inside another list (a request's item lists, at any object depth) hold at most
/// `max_items` elements, lists inside a list at most [`MAX_NUMBERS`]. serde buffers a whole
/// internally tagged enum before it decodes it, so a bound applied while decoding comes too
/// late for those; this one comes first. Malformed JSON passes: the parser names its error.
pub fn check_shape(bytes: &[u8], max_items: usize) -> Result<(), ShapeError> {
    // Per open container: `Some(elements so far)` for a list, `None` for an object.
    let mut open: Vec<Option<usize>> = Vec::new();
    let mut lists_open = 0usize;
    let mut in_string = false;
    let mut escaped = false;
    for &b in bytes {
        if in_string {
            match (escaped, b) {
                (true, _) => escaped = false,
                (false, b'\\') => escaped = true,
                (false, b'"') => in_string = false,
                _ => {}
            }
            continue;
        }
        // The first element of a list counts when it starts.
        if let Some(Some(0)) = open.last() {
            if !b.is_ascii_whitespace() && b != b']' {
                count_element(&mut open, lists_open, max_items)?;
            }
        }
        match b {
            b'"' => in_string = true,
            b'[' => {
                open.push(Some(0));
                lists_open += 1;
            }
            b'{' => open.push(None),
            b']' | b'}' => {
                if let Some(Some(_)) = open.pop() {
                    lists_open -= 1;
                }
            }
            b',' if matches!(open.last(), Some(Some(_))) => {
                count_element(&mut open, lists_open, max_items)?
            }
            _ => {}
        }
    }
    Ok(())
}

fn count_element(
    open: &mut [Option<usize>],
    lists_open: usize,
    max_items: usize,
) -> Result<(), ShapeError> {
    let Some(Some(elements)) = open.last_mut() else {
        return Ok(());
    };
    *elements += 1;
    match lists_open {
        1 if *elements > max_items => Err(ShapeError::TooManyItems { limit: max_items }),
        1 => Ok(()),
        _ if *elements > MAX_NUMBERS => Err(ShapeError::TooManyNumbers),
        _ => Ok(()),
    }
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
    fn the_shape_check_bounds_item_lists_and_the_lists_inside_them() {
        let numbers = |n: usize| vec!["0.5"; n].join(",");
        let inside = |n: usize| format!(r#"{{"factors": [{{"information": [{}]}}]}}"#, numbers(n));
        assert_eq!(check_shape(inside(MAX_NUMBERS).as_bytes(), 10), Ok(()));
        assert_eq!(
            check_shape(inside(MAX_NUMBERS + 1).as_bytes(), 10),
            Err(ShapeError::TooManyNumbers)
        );
        let outer = |n: usize| format!(r#"{{"op": "x", "batch": {{"fix": [{}]}}}}"#, numbers(n));
        assert_eq!(check_shape(outer(7).as_bytes(), 7), Ok(()));
        assert_eq!(
            check_shape(outer(8).as_bytes(), 7),
            Err(ShapeError::TooManyItems { limit: 7 })
        );
        // Brackets and commas inside strings are text; empty lists hold nothing.
        let text = r#"{"a": ["[,,,]", "\"[,]"], "b": [], "c": [ ]}"#;
        assert_eq!(check_shape(text.as_bytes(), 2), Ok(()));
        assert_eq!(check_shape(b"[[]]", 1), Ok(()));
        assert_eq!(
            check_shape(b"[1,2", 1),
            Err(ShapeError::TooManyItems { limit: 1 })
        );
    }
}
