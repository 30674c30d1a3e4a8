//! Shared test support: where the benchmark data lives, and synthetic fixtures made by code.
#![allow(dead_code)]

#[allow(dead_code)]
pub mod fusion;
pub mod server;

use std::fmt::Write as _;
use std::path::PathBuf;

use factord::factors::testing::Rng;
use factord::geometry::Se2;

/// The shared data directory (`FACTORD_DATA`, default `../shared/data` next to the checkout).
/// Returns `None` (after saying why) when it is missing; under `CI=true` a missing dataset fails.
pub fn data_file(relative: &str) -> Option<PathBuf> {
    let dir = std::env::var_os("FACTORD_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data"));
    let path = dir.join(relative);
    if path.is_file() {
        return Some(path);
    }
    if std::env::var("CI").is_ok_and(|v| v == "true") {
        panic!("dataset {} is missing and CI=true", path.display());
    }
    eprintln!(
        "skipping: dataset {} not found (set FACTORD_DATA)",
        path.display()
    );
    None
}

/// A noisy 2D "Manhattan" pose graph as g2o text: a random walk on a grid with odometry and
/// loop closures to earlier poses nearby, measured with noise; initial guess from odometry.
pub fn synthetic_manhattan(poses: usize, seed: u64) -> String {
    let mut rng = Rng::new(seed);
    let mut truth = vec![Se2::identity()];
    for _ in 1..poses {
        let turn = match rng.next_u64() % 4 {
            0 => std::f64::consts::FRAC_PI_2,
            1 => -std::f64::consts::FRAC_PI_2,
            _ => 0.0,
        };
        let last = *truth.last().unwrap();
        truth.push(last.compose(&Se2::new(1.0, 0.0, turn)));
    }
    let (sigma_t, sigma_r) = (0.05, 0.01);
    let noisy = |rng: &mut Rng, z: Se2| {
        Se2::new(
            z.x + sigma_t * rng.normal(),
            z.y + sigma_t * rng.normal(),
            z.theta + sigma_r * rng.normal(),
        )
    };
    let info = format!(
        "{} 0 0 {} 0 {}",
        1.0 / (sigma_t * sigma_t),
        1.0 / (sigma_t * sigma_t),
        1.0 / (sigma_r * sigma_r)
    );
    let mut edges = String::new();
    let mut guess = vec![Se2::identity()];
    for i in 1..poses {
        let z = noisy(&mut rng, truth[i - 1].between(&truth[i]));
        guess.push(guess[i - 1].compose(&z));
        let _ = writeln!(
            edges,
            "EDGE_SE2 {} {} {} {} {} {info}",
            i - 1,
            i,
            z.x,
            z.y,
            z.theta
        );
        for j in 0..i.saturating_sub(3) {
            let d = truth[j].between(&truth[i]);
            if d.x.hypot(d.y) < 1.1 && rng.uniform() < 0.5 {
                let z = noisy(&mut rng, d);
                let _ = writeln!(edges, "EDGE_SE2 {j} {i} {} {} {} {info}", z.x, z.y, z.theta);
            }
        }
    }
    let mut out = String::new();
    for (i, p) in guess.iter().enumerate() {
        let _ = writeln!(out, "VERTEX_SE2 {i} {} {} {}", p.x, p.y, p.theta);
    }
    out + &edges
}

/// A fresh directory, unique within this test process.
pub fn temp_dir(name: &str) -> PathBuf {
    static NEXT: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
    let dir = std::env::temp_dir().join(format!("factord-test-{}-{name}-{n}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A noisy 3D pose graph as g2o text: a rising helix with odometry and loop closures between
/// poses one turn apart; initial guess from composing the noisy odometry.
pub fn synthetic_helix_3d(poses: usize, seed: u64) -> String {
    use factord::geometry::Se3;
    use nalgebra::{UnitQuaternion, Vector3, Vector6};
    let mut rng = Rng::new(seed);
    let per_turn = 20;
    let step = Se3::new(
        UnitQuaternion::from_euler_angles(0.0, 0.02, 2.0 * std::f64::consts::PI / per_turn as f64),
        Vector3::new(1.0, 0.0, 0.05),
    );
    let mut truth = vec![Se3::identity()];
    for i in 1..poses {
        truth.push(truth[i - 1].compose(&step));
    }
    let (sigma_t, sigma_r) = (0.02, 0.005);
    let mut noisy = |z: Se3| {
        let n = Vector6::from_fn(|i, _| {
            if i < 3 {
                sigma_t * rng.normal()
            } else {
                sigma_r * rng.normal()
            }
        });
        z.compose(&Se3::exp(&n))
    };
    // Information for our (translation, angle) error, written in g2o's half-angle convention.
    let (it, ir) = (1.0 / (sigma_t * sigma_t), 4.0 / (sigma_r * sigma_r));
    let info = format!("{it} 0 0 0 0 0 {it} 0 0 0 0 {it} 0 0 0 {ir} 0 0 {ir} 0 {ir}");
    let fmt = |p: &Se3| {
        let q = p.rotation.quaternion();
        format!(
            "{} {} {} {} {} {} {}",
            p.translation.x, p.translation.y, p.translation.z, q.i, q.j, q.k, q.w
        )
    };
    let mut edges = String::new();
    let mut guess = vec![Se3::identity()];
    for i in 1..poses {
        let z = noisy(truth[i - 1].between(&truth[i]));
        guess.push(guess[i - 1].compose(&z));
        let _ = writeln!(edges, "EDGE_SE3:QUAT {} {i} {} {info}", i - 1, fmt(&z));
        if i >= per_turn {
            let j = i - per_turn;
            let z = noisy(truth[j].between(&truth[i]));
            let _ = writeln!(edges, "EDGE_SE3:QUAT {j} {i} {} {info}", fmt(&z));
        }
    }
    let mut out = String::new();
    for (i, p) in guess.iter().enumerate() {
        let _ = writeln!(out, "VERTEX_SE3:QUAT {i} {}", fmt(p));
    }
    out + &edges
}

/// Under `CI=true` a missing prerequisite is a failure; otherwise the test is skipped.
#[allow(dead_code)]
pub fn skip_or_fail<T>(reason: &str) -> Option<T> {
    if std::env::var("CI").is_ok_and(|v| v == "true") {
        panic!("{reason} (CI=true)");
    }
    eprintln!("skipping: {reason}");
    None
}

/// The python of the venv `~/.cache/factord/venvs/<name>`, created if missing, after
/// `pip install <args>` of each entry of `installs` (PyPI must be reachable the first time).
#[allow(dead_code)]
pub fn python_venv(name: &str, installs: &[Vec<std::ffi::OsString>]) -> Result<PathBuf, String> {
    use std::process::Command;
    let home = std::env::var_os("HOME").ok_or("HOME is not set")?;
    let venv = PathBuf::from(home).join(".cache/factord/venvs").join(name);
    let python = venv.join("bin/python");
    let run = |cmd: &mut Command| -> Result<(), String> {
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
    };
    if !python.exists() {
        run(Command::new("python3").args(["-m", "venv"]).arg(&venv))?;
    }
    for args in installs {
        run(Command::new(&python)
            .args([
                "-m",
                "pip",
                "install",
                "--quiet",
                "--disable-pip-version-check",
            ])
            .args(args))?;
    }
    Ok(python)
}
