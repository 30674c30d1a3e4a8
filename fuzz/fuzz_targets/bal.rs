//! The BAL reader (`factord::io::bal::parse`) on arbitrary text. Only panics are failures.
#![no_main]

use std::path::Path;

use factord_fuzz::verbose;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let result = factord::io::bal::parse(Path::new("fuzz.bal"), text);
    if verbose() {
        eprintln!("bal: {:?}", result.map(|b| (b.num_cameras, b.num_points)));
    }
});
