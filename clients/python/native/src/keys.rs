//! Keys as GTSAM makes them: `symbol('x', 1)` is `('x' << 56) | 1`, `X(1)` its shorthand. A key
//! whose top byte is a letter is written back in that shorthand (`X(1)`), any other as its number.

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use factord::problem::Key;

const INDEX_BITS: u32 = 56;
const INDEX_MASK: Key = (1 << INDEX_BITS) - 1;

/// `('c' << 56) | index`, refusing a character that is not one byte or an index of 56 bits or more.
pub fn make_symbol(chr: char, index: u64) -> PyResult<Key> {
    if !chr.is_ascii() || chr == '\0' {
        return Err(PyValueError::new_err(format!(
            "a symbol's character must be one ASCII character, got {chr:?}"
        )));
    }
    if index > INDEX_MASK {
        return Err(PyValueError::new_err(format!(
            "a symbol's index must be below 2^56, got {index}"
        )));
    }
    Ok(((chr as u64) << INDEX_BITS) | index)
}

/// `X(1)` for a symbol of a letter, the number otherwise.
pub fn key_name(key: Key) -> String {
    let chr = (key >> INDEX_BITS) as u8;
    if chr.is_ascii_alphabetic() {
        format!("{}({})", chr.to_ascii_uppercase() as char, key & INDEX_MASK)
    } else {
        key.to_string()
    }
}

/// `symbol('x', 1)`: the key of variable 1 of the family `x`.
#[pyfunction]
#[pyo3(signature = (chr, index))]
pub fn symbol(chr: char, index: u64) -> PyResult<Key> {
    make_symbol(chr, index)
}

/// The character of a symbol key (`symbolChr(X(1)) == 'x'`).
#[pyfunction]
#[pyo3(name = "symbolChr")]
pub fn symbol_chr(key: Key) -> char {
    ((key >> INDEX_BITS) as u8) as char
}

/// The index of a symbol key (`symbolIndex(X(1)) == 1`).
#[pyfunction]
#[pyo3(name = "symbolIndex")]
pub fn symbol_index(key: Key) -> u64 {
    key & INDEX_MASK
}

/// `X(1)` for `symbol('x', 1)`: how errors name keys.
#[pyfunction]
#[pyo3(name = "keyName")]
pub fn key_name_py(key: Key) -> String {
    key_name(key)
}
