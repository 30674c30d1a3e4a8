//! The Python side, run by the one test command: the scripted client (HTTP and zenoh, the robot
//! example), the numpy client with auth on, and the wire-schema check of `proto/` against a live
//! server.
//!
//! They need a virtual environment with the client package (which brings `numpy` and
//! `eclipse-zenoh`) and `jsonschema`; this test creates it once under
//! `~/.cache/factord/venvs/client` (PyPI must be reachable).
//! Without Python or PyPI it skips with the reason, except under `CI=true`, where it fails.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use common::server::TestServer;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The venv's python, created and filled on first use.
fn python() -> Option<PathBuf> {
    static PYTHON: OnceLock<Result<PathBuf, String>> = OnceLock::new();
    let result = PYTHON.get_or_init(|| {
        // Reinstalling the local package is cheap and keeps the venv in step with the checkout.
        common::python_venv(
            "client",
            &[
                vec!["jsonschema>=4.18".into(), "referencing".into()],
                vec![repo().join("clients/python").into()],
            ],
        )
    });
    match result {
        Ok(p) => Some(p.clone()),
        Err(reason) => {
            common::skip_or_fail(&format!("no Python environment for the client: {reason}"))
        }
    }
}

fn data_dir() -> PathBuf {
    std::env::var_os("FACTORD_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| repo().join("../shared/data"))
}

fn run_script(python: &Path, args: &[&str]) {
    // One script at a time: they time acknowledgements over real zenoh sessions, and four of
    // them at once on two cores made the recovery script miss a duplicate ack's timing.
    static ONE_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _turn = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let out = Command::new(python)
        .args(args)
        .current_dir(repo())
        .output()
        .expect("python runs");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    println!("{stdout}");
    assert!(out.status.success(), "{args:?} failed:\n{stdout}\n{stderr}");
}

#[test]
fn python_client_over_http_and_zenoh() {
    let Some(python) = python() else { return };
    let server = TestServer::start(&[]);
    let data = data_dir();
    run_script(
        &python,
        &[
            "clients/python/tests/test_client.py",
            "--http",
            &server.http,
            "--zenoh",
            &server.zenoh,
            "--data-dir",
            data.to_str().expect("utf-8 path"),
        ],
    );
    server.assert_no_panic();
}

#[test]
fn wire_schema_matches_the_server() {
    let Some(python) = python() else { return };
    let server = TestServer::start(&[]);
    run_script(&python, &["proto/validate.py", "--server", &server.http]);
    server.assert_no_panic();
}

/// The recovering client (issue 17): HTTP retry rules against a scripted network peer, then
/// streams over zenoh and HTTP against factord processes the script starts, kills (-9) and
/// restarts itself (so it gets this build's binary).
#[test]
fn python_client_recovers() {
    let Some(python) = python() else { return };
    run_script(&python, &["clients/python/tests/test_http_retry.py"]);
    let data = data_dir();
    run_script(
        &python,
        &[
            "clients/python/tests/test_recovery.py",
            "--factord",
            env!("CARGO_BIN_EXE_factord"),
            "--data-dir",
            data.to_str().expect("utf-8 path"),
        ],
    );
}

/// The numpy client (issue 19): poses, noise, batches from arrays and a method per route of
/// `proto/v1/openapi.json` without a server; then against a factord with tokens that the script
/// starts itself: the 15-line intel example with and without a token, covariance in and out,
/// exports with stamps over HTTP and zenoh, one exception family, and a script that forgets
/// `close()` exiting at once.
#[test]
fn python_client_numpy_and_auth() {
    let Some(python) = python() else { return };
    run_script(&python, &["clients/python/tests/test_helpers.py"]);
    let data = data_dir();
    run_script(
        &python,
        &[
            "clients/python/tests/test_numpy_auth.py",
            "--factord",
            env!("CARGO_BIN_EXE_factord"),
            "--data-dir",
            data.to_str().expect("utf-8 path"),
        ],
    );
}
