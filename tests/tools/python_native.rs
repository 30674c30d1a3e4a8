//! The in-process Python package `factord` (issue 56, item 2: PyO3 + maturin, GTSAM's names),
//! built and tested by the one test command.
//!
//! The wheel is built with `maturin build --release --locked` in this run's own
//! `CARGO_TARGET_DIR` (the factord library and its dependencies are already compiled there, so
//! only PyO3 and the binding compile), then installed with pip into a directory of this run (not
//! into the shared venv, which holds only maturin, numpy and pytest: two checkouts testing at
//! once cannot see each other's build). Then:
//! - `clients/python/native/tests/test_inprocess.py` (pytest): keys, geometry, the typed errors
//!   naming keys as `X(1)`, noise weights, an ISAM2 stream against the batch optimum, g2o round
//!   trips;
//! - `clients/python/native/tests/test_user_factors.py` (pytest): `CustomFactor` (Python error
//!   functions with GTSAM-convention Jacobians, also on an iSAM2 update's second thread) and
//!   `FactorType` (Python functions recorded into the expression language);
//! - `clients/python/native/tests/test_session.py` (pytest): `IncrementalSession`, a server
//!   session in process through the service's command API (M3500 streamed to the batch
//!   optimum, refusals with the server's error body, two sessions in two threads);
//! - `clients/python/native/tests/one_wheel.py`: the wheel's wire client (`factord_client`)
//!   against a test server, the same factor type in process and on the server;
//! - `clients/python/native/tests/gtsam_parity.py`: the same scripts with `import gtsam` (the
//!   `gtsam` venv) and `import factord as gtsam`, compared (GTSAM's Pose2SLAMExample and
//!   PlanarSLAMExample to 1e-9, M3500 through readG2o and a Pose3 loop by cross-scoring).
//!
//! Without Python, PyPI or the datasets this skips with the reason, except under `CI=true`,
//! where it fails.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;
use std::time::Instant;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The target directory this test binary was built in (`<target>/release/deps/tools-…`), unless
/// `CARGO_TARGET_DIR` names one.
fn target_dir() -> PathBuf {
    if let Some(dir) = std::env::var_os("CARGO_TARGET_DIR") {
        return PathBuf::from(dir);
    }
    let exe = std::env::current_exe().expect("the test binary has a path");
    exe.ancestors()
        .nth(3)
        .expect("the test binary is in <target>/<profile>/deps")
        .to_path_buf()
}

/// The venv's python and the directory the freshly built package is installed in.
struct Installed {
    python: PathBuf,
    site: PathBuf,
}

fn run(cmd: &mut Command) -> Result<String, String> {
    let out = cmd.output().map_err(|e| format!("{cmd:?}: {e}"))?;
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    if out.status.success() {
        Ok(stdout)
    } else {
        Err(format!(
            "{cmd:?} failed:\n{stdout}\n{}",
            String::from_utf8_lossy(&out.stderr)
        ))
    }
}

/// Builds the wheel and installs it into a directory of this run.
fn build(python: &Path) -> Result<PathBuf, String> {
    let scratch = common::temp_dir("python-native");
    let wheels = scratch.join("wheels");
    let site = scratch.join("site");
    let start = Instant::now();
    let mut maturin = Command::new(python);
    // Not the variables cargo gives this test process: a dependency's build script that reads
    // one (ring reads CARGO_MANIFEST_DIR) would count as changed, and the shared dependencies
    // would be compiled again here and once more by the next `cargo test` (2 × 2–4 minutes).
    for (name, _) in std::env::vars_os() {
        let name = name.to_string_lossy();
        if name.starts_with("CARGO_PKG_")
            || name.starts_with("CARGO_BIN_")
            || [
                "CARGO_MANIFEST_DIR",
                "CARGO_MANIFEST_PATH",
                "CARGO_CRATE_NAME",
                "CARGO_PRIMARY_PACKAGE",
                "CARGO_TARGET_TMPDIR",
                "CARGO_RUSTC_CURRENT_DIR",
            ]
            .contains(&name.as_ref())
        {
            maturin.env_remove(name.as_ref());
        }
    }
    run(maturin
        .args(["-m", "maturin", "build", "--release", "--locked", "--quiet"])
        .arg("--manifest-path")
        .arg(repo().join("clients/python/native/Cargo.toml"))
        .arg("--interpreter")
        .arg(python)
        .arg("--out")
        .arg(&wheels)
        .env("CARGO_TARGET_DIR", target_dir()))?;
    let built = start.elapsed();
    let wheel = std::fs::read_dir(&wheels)
        .map_err(|e| format!("{}: {e}", wheels.display()))?
        .filter_map(Result::ok)
        .map(|e| e.path())
        .find(|p| p.extension().is_some_and(|x| x == "whl"))
        .ok_or("maturin built no wheel")?;
    run(Command::new(python)
        .args([
            "-m",
            "pip",
            "install",
            "--quiet",
            "--disable-pip-version-check",
            "--no-deps",
            "--target",
        ])
        .arg(&site)
        .arg(&wheel))?;
    println!(
        "built {} in {:.1} s, installed in {:.1} s",
        wheel.file_name().unwrap_or_default().to_string_lossy(),
        built.as_secs_f64(),
        (start.elapsed() - built).as_secs_f64()
    );
    Ok(site)
}

/// The venv (made once) and this run's build of the package, or `None` (skipped; a failure
/// under CI).
fn installed() -> Option<&'static Installed> {
    static INSTALLED: OnceLock<Result<Installed, String>> = OnceLock::new();
    let result = INSTALLED.get_or_init(|| {
        let python = common::python_venv(
            "native",
            &[vec![
                "maturin>=1.9,<2".into(),
                "numpy>=1.23".into(),
                "pytest>=7".into(),
            ]],
        )?;
        let site = build(&python)?;
        Ok(Installed { python, site })
    });
    match result {
        Ok(installed) => Some(installed),
        Err(reason) => common::skip_or_fail(&format!(
            "cannot build the in-process Python package: {reason}"
        )),
    }
}

/// The shared data directory, if the datasets the scripts read are there.
fn data_dir() -> Option<PathBuf> {
    let m3500 = common::data_file("2d/carlone/input_M3500_g2o.g2o")?;
    common::data_file("2d/carlone/input_INTEL_g2o.g2o")?;
    Some(
        m3500
            .ancestors()
            .nth(3)
            .expect("<data>/2d/carlone/file")
            .to_path_buf(),
    )
}

fn python_in(installed: &Installed, data: &Path) -> Command {
    let mut cmd = Command::new(&installed.python);
    cmd.current_dir(repo())
        .env("PYTHONPATH", &installed.site)
        .env("FACTORD_DATA", data)
        .env("PYTHONDONTWRITEBYTECODE", "1");
    cmd
}

#[test]
fn inprocess_python_api_passes_its_tests() {
    let Some(installed) = installed() else { return };
    let Some(data) = data_dir() else { return };
    let start = Instant::now();
    let out = run(python_in(installed, &data).args([
        "-m",
        "pytest",
        "-q",
        "-s",
        "-p",
        "no:cacheprovider",
        "clients/python/native/tests/test_inprocess.py",
        "clients/python/native/tests/test_user_factors.py",
        "clients/python/native/tests/test_session.py",
    ]));
    match out {
        Ok(stdout) => println!(
            "{stdout}\npytest took {:.1} s",
            start.elapsed().as_secs_f64()
        ),
        Err(failure) => panic!("{failure}"),
    }
}

#[test]
fn inprocess_python_matches_gtsam() {
    let Some(installed) = installed() else { return };
    let Some(data) = data_dir() else { return };
    let Some(gtsam) = common::environments::gtsam_python() else {
        return;
    };
    let scratch = common::temp_dir("gtsam-parity");
    let start = Instant::now();
    let out = run(python_in(installed, &data)
        .arg("clients/python/native/tests/gtsam_parity.py")
        .arg("--gtsam-python")
        .arg(&gtsam)
        .arg("--data-dir")
        .arg(&data)
        .arg("--scratch")
        .arg(&scratch));
    match out {
        Ok(stdout) => println!(
            "{stdout}\nparity took {:.1} s",
            start.elapsed().as_secs_f64()
        ),
        Err(failure) => panic!("{failure}"),
    }
}

/// `factord.solve` in process gives what `factord solve` prints: the same reader, the same
/// defaults, the same optimum, to the last digits.
#[test]
fn inprocess_solve_matches_the_cli() {
    let Some(installed) = installed() else { return };
    let Some(data) = data_dir() else { return };
    for (file, method) in [
        ("2d/carlone/input_INTEL_g2o.g2o", "gn"),
        ("2d/carlone/input_M3500_g2o.g2o", "lm"),
    ] {
        let path = data.join(file);
        let cli = run(Command::new(env!("CARGO_BIN_EXE_factord"))
            .args([
                "solve",
                "--quiet",
                "--method",
                method,
                "--summary-json",
                "-",
            ])
            .arg(&path))
        .unwrap_or_else(|failure| panic!("{failure}"));
        let summary: serde_json::Value =
            serde_json::from_str(&cli[cli.find('{').expect("a JSON summary")..])
                .expect("the summary is JSON");
        let script = format!(
            "import factord, json\n\
             g, v = factord.readG2o({path:?}, False)\n\
             _, s = factord.solve(g, v, method={method:?}, initialization='auto')\n\
             print(json.dumps([s['final_chi2'], s['iterations']]))"
        );
        let out = run(python_in(installed, &data).args(["-c", &script]))
            .unwrap_or_else(|failure| panic!("{failure}"));
        let (chi2, iterations): (f64, usize) =
            serde_json::from_str(out.trim()).expect("two numbers");
        let expected = summary["final_chi2"].as_f64().expect("final_chi2");
        println!(
            "{file} ({method}): CLI chi2 {expected}, in process {chi2}, {iterations} iterations"
        );
        assert!(
            (chi2 - expected).abs() <= 1e-12 * expected,
            "{file}: in process {chi2}, factord solve {expected}"
        );
        assert_eq!(
            Some(iterations as u64),
            summary["iterations"].as_u64(),
            "{file}"
        );
    }
}

/// The one wheel carries the wire client too: a factor type written in Python is solved in
/// process and, as the same definition, by a running server reached with `factord_client` from
/// the same wheel; the two optima agree (`clients/python/native/tests/one_wheel.py`).
#[test]
fn one_wheel_solves_in_process_and_on_a_server() {
    let Some(installed) = installed() else { return };
    let Some(data) = data_dir() else { return };
    let server = common::server::TestServer::start(&[]);
    let out = run(python_in(installed, &data)
        .arg("clients/python/native/tests/one_wheel.py")
        .arg(server.url("")));
    match out {
        Ok(stdout) => println!("{stdout}"),
        Err(failure) => panic!("{failure}"),
    }
    server.assert_no_panic();
}
