//! Trajectories with time: variables carry the robot's `stamp`, and the estimate is served as the
//! files trajectory tools read (`estimate?format=tum|kitti|g2o|ply`, over HTTP and the zenoh
//! estimate queryable), also after kill -9; a window session exports its lag-smoothed
//! trajectory, and evo's `evo_ape` reads that export against EuRoC's ground truth.

use crate::common;

use std::process::Command;
use std::time::Duration;

use crate::common::eval::experiment::run_smoothed;
use common::fusion::{inputs, keyframe_batches, start_message};
use common::server::{client, create, get, post, post_raw, zenoh_peer, TestServer};
use serde_json::{json, Value};

/// Three stamped poses (a square's corner), odometry between them, a fixed first pose.
fn stamped_batch() -> Value {
    let between = |a: u64, b: u64, m: [f64; 3]| json!({"type": "between_se2", "keys": [a, b], "measurement": m, "sigmas": [0.1, 0.1, 0.05]});
    json!({
        "variables": [
            {"key": 0, "kind": "se2", "value": [0.0, 0.0, 0.0], "fixed": true, "stamp": 1700000000.125},
            {"key": 1, "kind": "se2", "value": [1.1, 0.1, 1.5], "stamp": 1700000000.225},
            {"key": 2, "kind": "se2", "value": [0.9, 1.2, 3.0], "stamp": 1700000000.325},
            {"key": 7, "kind": "point2", "value": [0.5, 0.5]}
        ],
        "factors": [
            between(0, 1, [1.0, 0.0, std::f64::consts::FRAC_PI_2]),
            between(1, 2, [1.0, 0.0, std::f64::consts::FRAC_PI_2]),
            {"type": "bearing_range_se2", "keys": [1, 7], "measurement": [2.0, 0.7], "sigmas": [0.1, 0.1]}
        ]
    })
}

async fn text(c: &reqwest::Client, url: &str) -> (u16, String, String) {
    let r = c.get(url).send().await.expect("request sent");
    let status = r.status().as_u16();
    let media = r
        .headers()
        .get("content-type")
        .map(|v| v.to_str().unwrap().to_string())
        .unwrap_or_default();
    (status, media, r.text().await.unwrap())
}

fn numbers(line: &str) -> Vec<f64> {
    line.split_whitespace()
        .map(|f| f.parse().unwrap_or_else(|e| panic!("{line}: {e}")))
        .collect()
}

/// Equal numbers, bit for bit: the JSON estimate and the files are both read exactly
/// (serde_json with `float_roundtrip`, Rust's own parser).
fn same(a: &[f64], b: &[f64]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
}

/// The TUM lines of `text` (comments skipped) as numbers.
fn tum_rows(text: &str) -> Vec<Vec<f64>> {
    text.lines()
        .filter(|l| !l.starts_with('#'))
        .map(numbers)
        .collect()
}

/// Checks the exports of session `s` against its JSON estimate: every number reads back
/// exactly, stamps order the trajectory, landmarks are only in g2o and PLY.
async fn check_exports(c: &reqwest::Client, server: &TestServer, s: &str) {
    let (status, estimate) = get(c, &server.url(&format!("/v1/sessions/{s}/estimate"))).await;
    assert_eq!(status, 200, "{estimate}");
    let vars = estimate["variables"].as_array().unwrap();
    let value = |key: u64| -> Vec<f64> {
        let v = vars.iter().find(|v| v["key"] == key).unwrap();
        serde_json::from_value(v["value"].clone()).unwrap()
    };
    assert_eq!(vars[1]["stamp"], 1700000000.225, "{estimate}");
    assert!(vars[3].get("stamp").is_none(), "{estimate}");

    let url = |format: &str| server.url(&format!("/v1/sessions/{s}/estimate?format={format}"));
    let (status, media, tum) = text(c, &url("tum")).await;
    assert_eq!(
        (status, media.as_str()),
        (200, "text/plain; charset=utf-8"),
        "{tum}"
    );
    let rows = tum_rows(&tum);
    assert_eq!(rows.len(), 3, "poses only:\n{tum}");
    for (row, (key, stamp)) in rows.iter().zip([(0, 0.125), (1, 0.225), (2, 0.325)]) {
        assert_eq!(row[0], 1700000000.0 + stamp);
        let [x, y, theta] = value(key)[..] else {
            panic!()
        };
        assert!(same(&row[1..4], &[x, y, 0.0]), "{row:?} vs {x} {y}");
        let yaw = 2.0 * row[6].atan2(row[7]);
        assert!((yaw - theta).abs() < 1e-12, "{yaw} vs {theta}");
    }

    let (_, _, kitti) = text(c, &url("kitti")).await;
    let m: Vec<Vec<f64>> = kitti.lines().map(numbers).collect();
    assert_eq!(m.len(), 3);
    assert!(same(&[m[2][3], m[2][7]], &value(2)[..2]), "{kitti}");

    let (_, _, g2o) = text(c, &url("g2o")).await;
    let lines: Vec<&str> = g2o.lines().collect();
    assert_eq!(lines.len(), 4, "{g2o}");
    assert!(lines[3].starts_with("VERTEX_XY 7 "));
    assert!(
        same(&numbers(&lines[2]["VERTEX_SE2 ".len()..])[1..], &value(2)),
        "{g2o}"
    );
    assert!(
        same(&numbers(&lines[3]["VERTEX_XY ".len()..])[1..], &value(7)),
        "{g2o}"
    );

    let (_, _, ply) = text(c, &url("ply")).await;
    assert!(ply.starts_with("ply\nformat ascii 1.0\n") && ply.contains("element vertex 4\n"));

    let (status, body) = get(c, &url("xml")).await;
    assert_eq!(status, 400, "{body}");
    assert!(body.to_string().contains("format"), "{body}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stamped_graph_exports_over_http_and_zenoh_and_after_kill_9() {
    let dir = common::temp_dir("export");
    // A snapshot after every second entry: the restart reads stamps from it, not only the log.
    let config = dir.with_extension("json");
    std::fs::write(
        &config,
        json!({"journal": {"snapshot_every": 2}}).to_string(),
    )
    .unwrap();
    let config = config.to_str().unwrap().to_string();
    let server = TestServer::start_at(&dir, &["--config", &config], &[]);
    let c = client();
    create(
        &c,
        &server,
        &json!({"session": "map", "kind": "pose_graph_2d"}),
    )
    .await;
    let (status, ack) = post(
        &c,
        &server.url("/v1/sessions/map/batches?wait=true"),
        &stamped_batch(),
    )
    .await;
    assert_eq!(status, 200, "{ack}");

    // A stamp that is not a number is refused and names its field; nothing is applied.
    let bad =
        json!({"variables": [{"key": 3, "kind": "se2", "value": [0, 0, 0], "stamp": "noon"}]});
    let (status, e) = post(&c, &server.url("/v1/sessions/map/batches"), &bad).await;
    assert_eq!(status, 400, "{e}");
    assert!(e.to_string().contains("stamp"), "{e}");
    let overflow = bad.to_string().replace("\"noon\"", "1e400");
    let (status, e) = post_raw(&c, &server.url("/v1/sessions/map/batches"), overflow).await;
    assert_eq!(status, 400, "{e}");
    let (status, ack) = post(
        &c,
        &server.url("/v1/sessions/map/optimize?wait=true"),
        &json!({}),
    )
    .await;
    assert_eq!(status, 200, "{ack}");
    check_exports(&c, &server, "map").await;

    // The zenoh estimate queryable serves the same text.
    let z = zenoh_peer(&server.zenoh).await;
    let (_, _, over_http) = text(&c, &server.url("/v1/sessions/map/estimate?format=tum")).await;
    let mut over_zenoh = None;
    for _ in 0..100 {
        let replies = z
            .get("factord/map/estimate?format=tum")
            .timeout(Duration::from_secs(5))
            .await
            .unwrap();
        if let Ok(reply) = replies.recv_async().await {
            let sample = reply.result().expect("an estimate, not an error");
            over_zenoh = Some(String::from_utf8(sample.payload().to_bytes().to_vec()).unwrap());
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(over_zenoh.as_deref(), Some(over_http.as_str()));
    z.close().await.unwrap();

    server.kill();
    let server = TestServer::start_at(&dir, &["--config", &config], &[]);
    // The restart rebuilds the session from its files and then solves it once more; until that
    // solve is done the estimate holds the values the snapshot and journal carry.
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    loop {
        let (status, stats) = get(&c, &server.url("/v1/sessions/map")).await;
        let solved =
            stats["recovering"] == false && stats["solving"] == false && stats["converged"] == true;
        if status == 200 && solved {
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "not solved after the restart: {status} {stats}"
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let (_, _, after) = text(&c, &server.url("/v1/sessions/map/estimate?format=tum")).await;
    // Same stamps; the values are the optimum again (a restart may solve once more: roundoff).
    let (after, before) = (tum_rows(&after), tum_rows(&over_http));
    assert_eq!(after.len(), before.len());
    for (a, b) in after.iter().zip(&before) {
        assert_eq!(a[0], b[0], "stamps survive kill -9");
        assert!(
            a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-12),
            "{a:?} vs {b:?}"
        );
    }
    check_exports(&c, &server, "map").await;
    server.assert_no_panic();
}

/// evo's `evo_ape`, from a venv made on first use (PyPI must be reachable then).
fn evo_ape() -> Option<std::path::PathBuf> {
    match common::python_venv("evo", &[vec!["evo".into()]]) {
        Ok(python) => Some(python.with_file_name("evo_ape")),
        Err(reason) => common::skip_or_fail(&format!("no evo: {reason}")),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn window_session_exports_its_smoothed_trajectory_for_evo() {
    let Some(inputs) = inputs(30.0, 10) else {
        return;
    };
    let server = TestServer::start(&[]);
    let c = client();
    create(
        &c,
        &server,
        &json!({"session": "robot", "kind": "sliding_window"}),
    )
    .await;
    let url = server.url("/v1/sessions/robot/fusion");
    let (status, reply) = post(&c, &url, &json!({"messages": [start_message(&inputs)]})).await;
    assert_eq!(status, 200, "{reply}");
    for batch in keyframe_batches(&inputs) {
        let (status, reply) = post(&c, &url, &json!({"messages": batch})).await;
        assert_eq!(status, 200, "{reply}");
    }
    let (status, _, tum) = text(&c, &server.url("/v1/sessions/robot/estimate?format=tum")).await;
    assert_eq!(status, 200, "{tum}");

    // The export is the library's lag-smoothed trajectory: each keyframe as it left the window,
    // then the window at its last optimum.
    let (_, smoothed) = run_smoothed(&inputs).unwrap();
    let rows = tum_rows(&tum);
    assert_eq!(rows.len(), inputs.keyframes.len() + 1, "every state once");
    for (row, want) in rows.iter().zip(&smoothed) {
        assert!((row[0] - want.t).abs() < 1e-9, "{} vs {}", row[0], want.t);
        for (got, want) in row[1..4].iter().zip(want.pose.position) {
            assert!((got - want).abs() < 1e-6, "{row:?} vs {:?}", want);
        }
    }

    // evo reads it against EuRoC's ground truth (absolute seconds; the session's clock starts
    // at the experiment's origin) and finds the APE we compute.
    let Some(evo_ape) = evo_ape() else { return };
    let dir = common::temp_dir("evo");
    std::fs::create_dir_all(&dir).unwrap();
    let estimate = dir.join("robot.tum");
    std::fs::write(&estimate, &tum).unwrap();
    let truth = common::data_file("imu/euroc_V1_01_easy/groundtruth_20hz_tum.txt").unwrap();
    let out = Command::new(&evo_ape)
        .arg("tum")
        .arg(&truth)
        .arg(&estimate)
        .args(["-r", "trans_part", "--t_max_diff", "0.001", "--no_warnings"])
        .args(["--t_offset", &inputs.origin.to_string()])
        .env("MPLBACKEND", "Agg")
        .output()
        .expect("evo_ape runs");
    let stdout = String::from_utf8_lossy(&out.stdout);
    println!("{stdout}");
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let statistic = |name: &str| -> f64 {
        let line = stdout
            .lines()
            .find(|l| l.trim_start().starts_with(name))
            .unwrap_or_else(|| panic!("no {name} in:\n{stdout}"));
        line.split_whitespace().last().unwrap().parse().unwrap()
    };
    // Ours: every exported state (the initial one too) against its ground-truth pose.
    let truths =
        std::iter::once(&inputs.initial_truth).chain(inputs.keyframes.iter().map(|k| &k.truth));
    let squares: Vec<f64> = truths
        .zip(&smoothed)
        .map(|(truth, state)| (state.pose.position() - truth.position()).norm_squared())
        .collect();
    let ours = (squares.iter().sum::<f64>() / squares.len() as f64).sqrt();
    let evo = statistic("rmse");
    assert!((evo - ours).abs() < 1e-6, "evo {evo} vs ours {ours}");
    server.assert_no_panic();
}
