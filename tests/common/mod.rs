//! Shared test support: where the benchmark data lives, and synthetic fixtures made by code.
#![allow(dead_code)]

pub mod ack_proxy;
pub mod bal_session;
pub mod browser;
pub mod cli;
pub mod docker;
pub mod environments;
#[path = "../../eval/mod.rs"]
pub mod eval;
pub mod fleet;
#[allow(dead_code)]
pub mod fusion;
pub mod m3500;
pub mod producer;
pub mod server;
pub mod square_walk;
pub mod wrong_closures;

#[allow(unused_imports)]
pub use environments::{gtsam_python, python_venv};

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

/// `between_se2` as a user-defined factor type (issue 18, item 4): `[R_ijᵀ (R_iᵀ (t_j − t_i) −
/// t_ij); wrap(θ_j − θ_i − θ_ij)]`, the built-in's residual.
pub fn user_between_se2() -> serde_json::Value {
    let e = serde_json::json!({"between": ["z", {"between": ["a", "b"]}]});
    serde_json::json!({
        "name": "user_between_se2",
        "variables": [{"name": "a", "kind": "se2"}, {"name": "b", "kind": "se2"}],
        "parameters": [{"name": "z", "kind": "se2"}],
        "residual": [{"translation": [e.clone()]}, {"wrap": [{"angle": [e]}]}],
        "description": "between_se2, written by a client"
    })
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
    // The poses on each grid cell, so that the loop closures of pose i look only at the earlier
    // poses within one cell of it (an all-pairs scan is quadratic: minutes at 100k poses). Every
    // pose within 1.1 m lies in the 3x3 cells around i, and they are visited in increasing order
    // as the scan did, so the random draws and the text are the same.
    let cell = |p: &Se2| (p.x.round() as i64, p.y.round() as i64);
    let mut on_cell: std::collections::HashMap<(i64, i64), Vec<usize>> = Default::default();
    let mut near = Vec::new();
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
        // The scan looked at j < i - 3.
        if i >= 4 {
            on_cell.entry(cell(&truth[i - 4])).or_default().push(i - 4);
        }
        let (cx, cy) = cell(&truth[i]);
        near.clear();
        for dx in -1..=1 {
            for dy in -1..=1 {
                near.extend(
                    on_cell
                        .get(&(cx + dx, cy + dy))
                        .into_iter()
                        .flatten()
                        .copied(),
                );
            }
        }
        near.sort_unstable();
        for &j in &near {
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

/// A 2D pose graph of a robot that stays in a `side` × `side` m building: a random walk on the
/// unit grid inside it, odometry edges, and `closures` loop closures per pose to random earlier
/// poses on the same or a neighbouring cell. Many poses per cell make the factorisation dense:
/// 60k poses in 40 m give a factor of 3e8 nonzeros (2.4 GB) and a 48 s factorisation, where
/// `synthetic_manhattan`'s 60k poses give 1.5e7 and 0.3 s. Guesses are the cells plus noise.
pub fn synthetic_building(poses: usize, seed: u64, side: i64, closures: usize) -> String {
    let mut rng = Rng::new(seed);
    let (mut x, mut y) = (0i64, 0i64);
    let mut cells = vec![(0i64, 0i64)];
    for _ in 1..poses {
        loop {
            let (dx, dy) = match rng.next_u64() % 4 {
                0 => (1, 0),
                1 => (-1, 0),
                2 => (0, 1),
                _ => (0, -1),
            };
            if (0..side).contains(&(x + dx)) && (0..side).contains(&(y + dy)) {
                (x, y) = (x + dx, y + dy);
                break;
            }
        }
        cells.push((x, y));
    }
    let info = "400 0 0 400 0 10000";
    let mut out = String::new();
    for (i, c) in cells.iter().enumerate() {
        let (gx, gy) = (0.1 * rng.normal(), 0.1 * rng.normal());
        let _ = writeln!(
            out,
            "VERTEX_SE2 {i} {} {} 0",
            c.0 as f64 + gx,
            c.1 as f64 + gy
        );
    }
    let mut on_cell: std::collections::HashMap<(i64, i64), Vec<usize>> = Default::default();
    for i in 1..poses {
        let (a, b) = (cells[i - 1], cells[i]);
        let (dx, dy) = ((b.0 - a.0) as f64, (b.1 - a.1) as f64);
        let _ = writeln!(out, "EDGE_SE2 {} {i} {dx} {dy} 0 {info}", i - 1);
        let near: Vec<usize> = [(0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)]
            .iter()
            .flat_map(|(dx, dy)| on_cell.get(&(b.0 + dx, b.1 + dy)).into_iter().flatten())
            .copied()
            .collect();
        for _ in 0..closures.min(near.len()) {
            let j = near[(rng.next_u64() % near.len() as u64) as usize];
            let (dx, dy) = ((b.0 - cells[j].0) as f64, (b.1 - cells[j].1) as f64);
            let _ = writeln!(out, "EDGE_SE2 {j} {i} {dx} {dy} 0 {info}");
        }
        if i >= 2 {
            on_cell.entry(cells[i - 2]).or_default().push(i - 2);
        }
    }
    out
}

/// A fresh directory, unique within this test process.
pub fn temp_dir(name: &str) -> PathBuf {
    static NEXT: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
    let dir = std::env::temp_dir().join(format!("factord-test-{}-{name}-{n}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    // A server's log lives beside its directory (`TestServer`) and is appended to: one left by
    // an earlier run whose process had the same id would be read as this run's.
    let _ = std::fs::remove_file(dir.with_extension("stderr"));
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

/// Runs `script` (a path in the repository) with `python` against `server` (`--http`,
/// `--zenoh`, then `extra`) from the repository root, printing its output; fails with that
/// output and the server's log when the script fails, and when the server panicked.
pub fn run_python_script(
    python: &std::path::Path,
    server: &server::TestServer,
    script: &str,
    extra: &[&str],
) {
    let out = std::process::Command::new(python)
        .arg(script)
        .args(["--http", &server.http, "--zenoh", &server.zenoh])
        .args(extra)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("python runs");
    let stdout = String::from_utf8_lossy(&out.stdout);
    println!("{stdout}");
    assert!(
        out.status.success(),
        "{script} failed:\n{stdout}\n{}\n--- factord:\n{}",
        String::from_utf8_lossy(&out.stderr),
        server.stderr()
    );
    server.assert_no_panic();
}
