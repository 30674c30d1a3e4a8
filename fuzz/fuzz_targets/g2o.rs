//! The g2o reader (`factord::io::g2o::parse`) on arbitrary text. Only panics are failures:
//! parse errors are the expected outcome for most inputs.
//!
//! A NUL byte splits the input into two files (vertices, then edges), as `factord::io::load`
//! reads a graph given with a separate edges file.
#![no_main]

use factord_fuzz::{text_files, verbose};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some(files) = text_files(data, "fuzz.g2o", ["fuzz-v.g2o", "fuzz-e.g2o"]) else {
        return;
    };
    let result = factord::io::g2o::parse(&files);
    if verbose() {
        eprintln!("g2o: {:?}", result.map(|g| g.problem.values.len()));
    }
});
