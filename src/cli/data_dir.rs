//! Where the datasets are: `FACTORD_DATA` (as the tests and benchmarks read it), else
//! `../shared/data` from the working directory. Every subcommand's default dataset lives under it,
//! and a relative input path that does not exist where the command runs is looked up there too,
//! so `factord solve 2d/carlone/input_M3500_g2o.g2o` works from any directory.

use std::path::{Path, PathBuf};

use super::CliError;

pub const DATA_ENV: &str = "FACTORD_DATA";
const DEFAULT_ROOT: &str = "../shared/data";

/// The data directory.
pub fn root() -> PathBuf {
    std::env::var_os(DATA_ENV)
        .filter(|v| !v.is_empty())
        .map_or_else(|| PathBuf::from(DEFAULT_ROOT), PathBuf::from)
}

/// `path` as given when it exists or is absolute; else the same relative path under [`root`] when
/// that exists; else `path` unchanged (so the error names what the user typed).
pub fn resolve(path: &Path) -> PathBuf {
    if path.is_absolute() || path.exists() {
        return path.to_path_buf();
    }
    let under_root = root().join(path);
    if under_root.exists() {
        under_root
    } else {
        path.to_path_buf()
    }
}

/// What a "not found" error adds, so the user knows both places were tried.
pub fn not_found_hint(path: &Path) -> String {
    if path.is_absolute() {
        return String::new();
    }
    format!(
        " (nor under the data directory {}; set {DATA_ENV} to it)",
        root().display()
    )
}

/// A directory argument, resolved as [`resolve`] does; an error naming `argument` when there is
/// no such directory.
pub fn existing_dir(argument: &str, path: &Path) -> Result<PathBuf, CliError> {
    let resolved = resolve(path);
    if resolved.is_dir() {
        return Ok(resolved);
    }
    Err(CliError::Argument {
        argument: argument.to_string(),
        reason: format!(
            "{}: no such directory{}",
            path.display(),
            not_found_hint(path)
        ),
    })
}
