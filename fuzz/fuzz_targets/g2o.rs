//! The g2o reader (`factord::io::g2o::parse`) on arbitrary text. Only panics are failures:
//! parse errors are the expected outcome for most inputs.
//!
//! A NUL byte splits the input into two files (vertices, then edges), as `factord::io::load`
//! reads a graph given with a separate edges file.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;

/// `FUZZ_VERBOSE=1` prints each input's outcome (for checking seeds and triaging).
fn verbose() -> bool {
    static V: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *V.get_or_init(|| std::env::var_os("FUZZ_VERBOSE").is_some())
}

fuzz_target!(|data: &[u8]| {
    // `load` reads files with `read_to_string`: the parser never sees invalid UTF-8.
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let result = match text.split_once('\0') {
        Some((vertices, edges)) => factord::io::g2o::parse(&[
            (Path::new("fuzz-v.g2o"), vertices),
            (Path::new("fuzz-e.g2o"), edges),
        ]),
        None => factord::io::g2o::parse(&[(Path::new("fuzz.g2o"), text)]),
    };
    if verbose() {
        eprintln!("g2o: {:?}", result.map(|g| g.problem.values.len()));
    }
});
