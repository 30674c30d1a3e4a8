//! What the fuzz targets share.

use std::path::Path;
use std::sync::OnceLock;

/// `FUZZ_VERBOSE=1` prints each input's outcome (for checking seeds and triaging).
pub fn verbose() -> bool {
    static V: OnceLock<bool> = OnceLock::new();
    *V.get_or_init(|| std::env::var_os("FUZZ_VERBOSE").is_some())
}

/// The input as the text files a graph reader is given, or None when it is not UTF-8 (`load`
/// reads files with `read_to_string`, so a reader never sees that). A NUL byte splits it into
/// two files named `split` (vertices, then edges), as a graph given with a separate edges file;
/// otherwise it is one file named `single`.
pub fn text_files<'a>(
    data: &'a [u8],
    single: &'static str,
    split: [&'static str; 2],
) -> Option<Vec<(&'static Path, &'a str)>> {
    let text = std::str::from_utf8(data).ok()?;
    Some(match text.split_once('\0') {
        Some((vertices, edges)) => vec![
            (Path::new(split[0]), vertices),
            (Path::new(split[1]), edges),
        ],
        None => vec![(Path::new(single), text)],
    })
}
