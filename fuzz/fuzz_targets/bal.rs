//! The BAL reader (`factord::io::bal::parse`) on arbitrary text. Only panics are failures.
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
    let result = factord::io::bal::parse(Path::new("fuzz.bal"), text);
    if verbose() {
        eprintln!("bal: {:?}", result.map(|b| (b.num_cameras, b.num_points)));
    }
});
