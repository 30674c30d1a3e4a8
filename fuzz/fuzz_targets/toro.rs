//! The TORO reader (`factord::io::toro::parse`: `VERTEX2`/`EDGE2`, `EQUIV`) on arbitrary text.
//! Only panics are failures.
//!
//! A NUL byte splits the input into two files, as the course's `-v.dat`/`-e.dat` pairs.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let _ = match text.split_once('\0') {
        Some((vertices, edges)) => factord::io::toro::parse(&[
            (Path::new("fuzz-v.dat"), vertices),
            (Path::new("fuzz-e.dat"), edges),
        ]),
        None => factord::io::toro::parse(&[(Path::new("fuzz.graph"), text)]),
    };
});
