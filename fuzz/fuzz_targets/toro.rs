//! The TORO reader (`factord::io::toro::parse`: `VERTEX2`/`EDGE2`, `EQUIV`) on arbitrary text.
//! Only panics are failures.
//!
//! A NUL byte splits the input into two files, as the course's `-v.dat`/`-e.dat` pairs.
#![no_main]

use factord_fuzz::{text_files, verbose};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some(files) = text_files(data, "fuzz.graph", ["fuzz-v.dat", "fuzz-e.dat"]) else {
        return;
    };
    let result = factord::io::toro::parse(&files);
    if verbose() {
        eprintln!("toro: {:?}", result.map(|g| g.problem.values.len()));
    }
});
