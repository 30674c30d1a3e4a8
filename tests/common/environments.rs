//! The environments tests share, made once under a lock: Python venvs
//! (`~/.cache/factord/venvs/<name>`) and, through [`locked`], the browser (`browser::install`).
//!
//! Tests of one binary run on parallel threads and several binaries may run at once, so
//! whatever they make in a shared place (a venv, a browser installed with apt) is made under an
//! OS lock (`flock` on `~/.cache/factord/locks/<name>.lock`; it conflicts between threads too,
//! since each takes it through its own open file), and a venv counts as made only once a marker
//! written after its creation exists: a venv left half-made by a killed run is made again. On
//! a fresh machine four tests once created the `ros2` venv at the same time, and two found
//! `bin/python` before pip was in it. `tests/tools/fresh_environments.rs` makes a venv from nothing,
//! from several threads at once, on every run.

use std::fs::File;
use std::path::{Path, PathBuf};
use std::process::Command;

/// `~/.cache/factord` (tests' shared environments live below it).
pub fn cache_dir() -> Result<PathBuf, String> {
    let home = std::env::var_os("HOME").ok_or("HOME is not set")?;
    Ok(PathBuf::from(home).join(".cache/factord"))
}

/// Runs `make` holding the lock `name` under `cache`: one at a time across threads and
/// processes.
pub fn locked<T>(cache: &Path, name: &str, make: impl FnOnce() -> T) -> Result<T, String> {
    let dir = cache.join("locks");
    std::fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let path = dir.join(format!("{name}.lock"));
    let file = File::create(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    file.lock()
        .map_err(|e| format!("locking {}: {e}", path.display()))?;
    let made = make();
    drop(file);
    Ok(made)
}

/// The python of the GTSAM venv (`pip install gtsam`), or `None` (skipped; a failure under CI).
pub fn gtsam_python() -> Option<PathBuf> {
    match python_venv("gtsam", &[vec!["gtsam".into()]]) {
        Ok(python) => Some(python),
        Err(reason) => super::skip_or_fail(&format!("no GTSAM Python environment: {reason}")),
    }
}

/// The python of the venv `~/.cache/factord/venvs/<name>`, created if missing, after
/// `pip install <args>` of each entry of `installs` (PyPI must be reachable the first time).
pub fn python_venv(name: &str, installs: &[Vec<std::ffi::OsString>]) -> Result<PathBuf, String> {
    python_venv_in(&cache_dir()?, name, installs, Pip::Cached)
}

/// Whether pip may use its download cache (`~/.cache/pip`).
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Pip {
    Cached,
    /// Everything downloaded again, as on a machine that never ran pip.
    NoCache,
}

/// [`python_venv`] with the venvs (and their locks) under `cache` instead of
/// `~/.cache/factord`.
pub fn python_venv_in(
    cache: &Path,
    name: &str,
    installs: &[Vec<std::ffi::OsString>],
    pip: Pip,
) -> Result<PathBuf, String> {
    let venv = cache.join("venvs").join(name);
    locked(cache, &format!("venv-{name}"), || {
        make_venv(&venv)?;
        let python = venv.join("bin/python");
        for args in installs {
            let mut install = Command::new(&python);
            install.args([
                "-m",
                "pip",
                "install",
                "--quiet",
                "--disable-pip-version-check",
            ]);
            if pip == Pip::NoCache {
                install.arg("--no-cache-dir");
            }
            run(install.args(args))?;
        }
        Ok(python)
    })?
}

/// Creates the venv at `venv` unless a complete one is there (its marker exists, or, for one
/// made before the marker, its pip runs); one left half-made is removed first.
fn make_venv(venv: &Path) -> Result<(), String> {
    let made = venv.join(".factord-venv-made");
    if made.exists() {
        return Ok(());
    }
    let python = venv.join("bin/python");
    // pip is the last thing `python -m venv` puts in.
    if python.exists() && run(Command::new(&python).args(["-m", "pip", "--version"])).is_ok() {
        return std::fs::write(&made, b"").map_err(|e| format!("{}: {e}", made.display()));
    }
    if venv.exists() {
        std::fs::remove_dir_all(venv).map_err(|e| format!("{}: {e}", venv.display()))?;
    }
    run(Command::new("python3").args(["-m", "venv"]).arg(venv))?;
    std::fs::write(&made, b"").map_err(|e| format!("{}: {e}", made.display()))
}

fn run(cmd: &mut Command) -> Result<(), String> {
    let out = cmd.output().map_err(|e| format!("{cmd:?}: {e}"))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "{cmd:?} failed:\n{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ))
    }
}
