//! The TORO reader (`factord::io::toro::parse`: `VERTEX2`/`EDGE2`, `EQUIV`) on arbitrary text.
//! Only panics are failures.
//!
//! A NUL byte splits the input into two files, as the course's `-v.dat`/`-e.dat` pairs.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;

/// `FUZZ_VERBOSE=1` prints each input's outcome (for checking seeds and triaging).
fn verbose() -> bool {
    static V: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *V.get_or_init(|| std::env::var_os("FUZZ_VERBOSE").is_some())
}

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let result = match text.split_once('\0') {
        Some((vertices, edges)) => factord::io::toro::parse(&[
            (Path::new("fuzz-v.dat"), vertices),
            (Path::new("fuzz-e.dat"), edges),
        ]),
        None => factord::io::toro::parse(&[(Path::new("fuzz.graph"), text)]),
    };
    if verbose() {
        eprintln!("toro: {:?}", result.map(|g| g.problem.values.len()));
    }
});
