//! The `sliding_window` session kind end to end: a robot's stream (EuRoC V1_01 IMU samples,
//! keyframes, relative poses and map priors made by `eval/experiment.rs`) over HTTP and over
//! zenoh, the states it publishes, and its refusals.

use crate::common;

use std::time::Duration;

use crate::common::eval::experiment::ape;
use crate::common::eval::fusion_client::run_over_zenoh;
use common::fusion::{inputs, keyframe_batches, position_error, start_message};
use common::server::{client, get, post, zenoh_get, zenoh_peer, TestServer};
use serde_json::{json, Value};

/// Creates the `sliding_window` session `robot`.
async fn create_window(c: &reqwest::Client, s: &TestServer) {
    let body = json!({"session": "robot", "kind": "sliding_window"});
    let (status, created) = post(c, &s.url("/v1/sessions"), &body).await;
    assert_eq!(status, 201, "{created}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sliding_window_over_http_tracks_and_refuses_bad_input() {
    let Some(inputs) = inputs(10.0, 10) else {
        return;
    };
    let s = TestServer::start(&[]);
    let c = client();
    create_window(&c, &s).await;
    let url = s.url("/v1/sessions/robot/fusion");
    let (status, reply) = post(&c, &url, &json!({"messages": [start_message(&inputs)]})).await;
    assert_eq!(status, 200, "{reply}");
    assert_eq!(reply["keyframes"], json!([0]));
    let mut errors = Vec::new();
    for batch in keyframe_batches(&inputs) {
        let (status, reply) = post(&c, &url, &json!({"messages": batch})).await;
        assert_eq!(status, 200, "{reply}");
        assert_eq!(reply["applied"], batch.len());
        errors.push(position_error(&inputs, &reply["latest"]));
    }
    assert_eq!(errors.len(), 100);
    let rmse = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt();
    assert!(rmse < 0.2, "APE rmse {rmse}");

    // Marginal covariances of the window's keyframes (15 × 15: pose, velocity, biases), the
    // joint one agreeing with them; a marginalised keyframe is not in the window.
    let (status, m) = get(
        &c,
        &s.url("/v1/sessions/robot/marginals?keys=100,91&joint=true"),
    )
    .await;
    assert_eq!(status, 200, "{m}");
    let joint: Vec<Vec<f64>> = serde_json::from_value(m["joint"].clone()).unwrap();
    assert_eq!(joint.len(), 30);
    for (v, offset) in m["variables"].as_array().unwrap().iter().zip([0, 15]) {
        assert_eq!(v["kind"], "nav_state", "{v}");
        let cov: Vec<Vec<f64>> = serde_json::from_value(v["covariance"].clone()).unwrap();
        assert_eq!(cov.len(), 15);
        for r in 0..15 {
            assert!(
                cov[r][r] > 0.0,
                "variance {r} of {}: {}",
                v["key"],
                cov[r][r]
            );
            for q in 0..15 {
                assert!((cov[r][q] - cov[q][r]).abs() <= 1e-9 * cov[r][r].max(cov[q][q]));
                assert!(
                    (cov[r][q] - joint[offset + r][offset + q]).abs()
                        <= 1e-12 + 1e-9 * cov[r][q].abs()
                );
            }
        }
        let sigma_position = (0..3).map(|r| cov[r][r]).sum::<f64>().sqrt();
        assert!(
            sigma_position > 1e-4 && sigma_position < 1.0,
            "position sigma {sigma_position} m"
        );
    }
    let (status, e) = get(&c, &s.url("/v1/sessions/robot/marginals?keys=0")).await;
    assert_eq!(status, 422, "{e}");
    assert_eq!(e["error"]["code"], "unknown_variable");
    assert_eq!(e["error"]["field"], "keys[0]");

    // Refusals name the message, keep what came before it, and leave the window usable.
    let last_t = inputs.keyframes.last().unwrap().t;
    let (status, e) = post(
        &c,
        &url,
        &json!({"messages": [
            {"type": "imu", "t": last_t + 0.01, "accel": [0, 0, 9.81], "gyro": [0, 0, 0]},
            {"type": "imu", "t": last_t + 0.01, "accel": [0, 0, 9.81], "gyro": [0, 0, 0]},
        ]}),
    )
    .await;
    assert_eq!(status, 422, "{e}");
    assert_eq!(e["error"]["field"], "messages[1]");
    assert!(
        e["error"]["message"]
            .as_str()
            .unwrap()
            .contains("not after"),
        "{e}"
    );
    let (status, e) = post(
        &c,
        &url,
        &json!({"messages": [
            {"type": "imu", "t": last_t + 0.02, "accel": [0, 0, 9.81], "gyro": [0, 0, 0]},
            {"type": "pose_prior", "key": 1, "position": [0, 0, 0], "rotation_xyzw": [0, 0, 0, 1],
             "sigma_position": 0.1, "sigma_rotation": 0.1},
        ]}),
    )
    .await;
    assert_eq!(status, 422, "{e}");
    assert!(
        e["error"]["message"]
            .as_str()
            .unwrap()
            .contains("not in the window"),
        "{e}"
    );
    let (status, e) = post(
        &c,
        &url,
        &json!({"messages": [{"type": "keyframe", "t": last_t + 0.1},
        {"type": "position_prior", "key": 101, "position": [0, 0, 0], "sigma": -1}]}),
    )
    .await;
    assert_eq!(status, 400, "{e}");
    assert_eq!(e["error"]["field"], "messages[1]");
    let (status, e) = post(&c, &url, &json!({"messages": [start_message(&inputs)]})).await;
    assert_eq!(status, 400, "{e}");
    let (status, e) = post(
        &c,
        &url,
        &json!({"messages": [{"type": "imu", "t": 1.0, "accel": [0, 0, "x"], "gyro": [0, 0, 0]}]}),
    )
    .await;
    assert_eq!(status, 400, "{e}");
    let (status, e) = post(
        &c,
        &s.url("/v1/sessions/robot/batches"),
        &json!({"variables": []}),
    )
    .await;
    assert_eq!(status, 400, "{e}");
    assert_eq!(e["error"]["code"], "wrong_kind");
    // The keyframe accepted before the bad prior is in the window; the session still works.
    let (status, reply) = post(
        &c,
        &url,
        &json!({"messages": [
        {"type": "imu", "t": last_t + 0.15, "accel": [0, 0, 9.81], "gyro": [0, 0, 0]},
        {"type": "keyframe", "t": last_t + 0.2}]}),
    )
    .await;
    assert_eq!(status, 200, "{reply}");
    assert_eq!(reply["keyframes"], json!([102]));
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sliding_window_over_zenoh_publishes_states_and_windows() {
    let Some(inputs) = inputs(20.0, 20) else {
        return;
    };
    let s = TestServer::start(&[]);
    // Window events, next to the states the robot side (`fusion::stream`) waits for.
    let z = zenoh_peer(&s.zenoh).await;
    let (_window_sub, windows) = common::server::json_samples(&z, "factord/rover/out/window").await;
    zenoh_get(&z, "factord/rpc", Some(&json!({"op": "health"})))
        .await
        .unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    let estimates = run_over_zenoh(&s.zenoh, "rover", &inputs).await.unwrap();
    assert_eq!(estimates.len(), 200);
    let (_, trans) = ape(&inputs, &estimates);
    assert!(trans.rmse < 0.2, "APE rmse {}", trans.rmse);
    assert!(estimates
        .iter()
        .all(|e| e.latency_seconds.is_some() && e.update_seconds > 0.0 && e.iterations > 0));
    let windows: Vec<Value> = windows.try_iter().collect();
    assert_eq!(windows.len(), 200);
    assert_eq!(
        windows.last().unwrap()["keyframes"]
            .as_array()
            .unwrap()
            .len(),
        20
    );
    // Every keyframe that left the window came out once, lag-smoothed, in order; they equal
    // the in-process experiment's lag-smoothed states.
    let smoothed: Vec<&Value> = windows
        .iter()
        .filter_map(|w| w["smoothed"].as_array())
        .flatten()
        .collect();
    assert_eq!(
        smoothed.len(),
        201 - 20,
        "the initial state and 200 keyframes, less 20 in the window"
    );
    let (_, expected) = crate::common::eval::experiment::run_smoothed(&inputs).unwrap();
    for (got, want) in smoothed.iter().zip(&expected) {
        let p: Vec<f64> = serde_json::from_value(got["position"].clone()).unwrap();
        assert!(
            p.iter()
                .zip(want.pose.position)
                .all(|(a, b)| (a - b).abs() < 1e-6),
            "{got} vs {:?}",
            want.pose
        );
    }
    s.assert_no_panic();
}

/// `factord fusion-eval --zenoh`: the experiment streamed to a running server as a robot would,
/// with evo's statistics and a TUM trajectory from the published states.
#[test]
fn fusion_eval_streams_to_a_running_server() {
    let Some(_) = inputs(1.0, 2) else {
        return;
    };
    let s = TestServer::start(&[]);
    let dir = common::temp_dir("fusion-eval");
    let tum = dir.join("estimate.tum");
    let imu = common::data_file("imu/euroc_V1_01_easy/imu0.csv").unwrap();
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_factord"))
        .args([
            "fusion-eval",
            "--seconds",
            "10",
            "--window",
            "5",
            "--json",
            "--zenoh",
        ])
        .arg(&s.zenoh)
        .arg("--data")
        .arg(imu.parent().unwrap())
        .arg("--tum-out")
        .arg(&tum)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let result: Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(result["through"], "zenoh");
    assert_eq!(result["keyframes"], 100);
    for stat in ["max", "mean", "median", "min", "rmse", "sse", "std"] {
        assert!(result["ape_trans"][stat].is_number(), "{result}");
        assert!(result["ape_full"][stat].is_number(), "{result}");
    }
    assert!(
        result["ape_trans"]["rmse"].as_f64().unwrap() < 0.2,
        "{result}"
    );
    let text = std::fs::read_to_string(&tum).unwrap();
    assert_eq!(text.lines().filter(|l| !l.starts_with('#')).count(), 100);
    // The session is deleted afterwards.
    s.assert_no_panic();
}

/// A keyframe from deltas pre-integrated on the robot, over HTTP: the same state as from the
/// raw samples.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn preintegrated_keyframes_over_http() {
    use factord::geometry::preintegration::{ImuNoise, Preintegrated};
    use nalgebra::Vector3;
    let s = TestServer::start(&[]);
    let c = client();
    let start = json!({"type": "start", "t": 0.005, "position": [0, 0, 0], "rotation_xyzw": [0, 0, 0, 1],
        "sigmas": {"position": 0.01, "rotation": 0.01, "velocity": 0.1, "accel_bias": 0.1, "gyro_bias": 0.01}});
    let samples: Vec<(f64, [f64; 3], [f64; 3])> = (1..=20)
        .map(|k| {
            (
                0.005 * k as f64,
                [0.1 * k as f64, 0.0, 9.81],
                [0.0, 0.01, 0.02],
            )
        })
        .collect();
    let end = 0.105;
    let mut on_robot = Preintegrated::new(ImuNoise::EUROC, Vector3::zeros(), Vector3::zeros());
    for (k, (t, a, w)) in samples.iter().enumerate() {
        let next = samples.get(k + 1).map_or(end, |s| s.0);
        on_robot.integrate(&Vector3::from(*a), &Vector3::from(*w), next - t);
    }
    let row_major = |m: &nalgebra::Matrix3<f64>| -> Vec<f64> {
        (0..3)
            .flat_map(|r| (0..3).map(move |c| m[(r, c)]))
            .collect()
    };
    let q = nalgebra::UnitQuaternion::from_matrix(&on_robot.delta_rotation);
    let keyframe = json!({"type": "preintegrated_keyframe", "t": end, "delta_t": on_robot.delta_t,
        "delta_rotation_xyzw": [q.i, q.j, q.k, q.w],
        "delta_velocity": on_robot.delta_velocity.as_slice(), "delta_position": on_robot.delta_position.as_slice(),
        "accel_bias": [0, 0, 0], "gyro_bias": [0, 0, 0],
        "d_rotation_d_gyro_bias": row_major(&on_robot.d_rotation_d_gyro_bias),
        "d_velocity_d_accel_bias": row_major(&on_robot.d_velocity_d_accel_bias),
        "d_velocity_d_gyro_bias": row_major(&on_robot.d_velocity_d_gyro_bias),
        "d_position_d_accel_bias": row_major(&on_robot.d_position_d_accel_bias),
        "d_position_d_gyro_bias": row_major(&on_robot.d_position_d_gyro_bias),
        "covariance": (0..15).flat_map(|r| (0..15).map(move |c| (r, c))).map(|(r, c)| on_robot.covariance[(r, c)]).collect::<Vec<_>>()});
    let raw: Vec<Value> = samples
        .iter()
        .map(|(t, a, w)| json!({"type": "imu", "t": t, "accel": a, "gyro": w}))
        .chain([json!({"type": "keyframe", "t": end})])
        .collect();
    let mut latest = Vec::new();
    for (name, messages) in [("raw", raw), ("delta", vec![keyframe.clone()])] {
        post(
            &c,
            &s.url("/v1/sessions"),
            &json!({"session": name, "kind": "sliding_window"}),
        )
        .await;
        let url = s.url(&format!("/v1/sessions/{name}/fusion"));
        let (status, reply) = post(&c, &url, &json!({"messages": [start.clone()]})).await;
        assert_eq!(status, 200, "{reply}");
        let (status, reply) = post(&c, &url, &json!({"messages": messages})).await;
        assert_eq!(status, 200, "{reply}");
        latest.push(reply["latest"].clone());
    }
    for field in ["position", "velocity"] {
        for i in 0..3 {
            let (a, b) = (
                latest[0][field][i].as_f64().unwrap(),
                latest[1][field][i].as_f64().unwrap(),
            );
            assert!((a - b).abs() < 1e-9, "{field}: {a} vs {b}");
        }
    }
    let mut short = keyframe;
    short["covariance"] = json!([1.0, 2.0]);
    let (status, e) = post(
        &c,
        &s.url("/v1/sessions/delta/fusion"),
        &json!({"messages": [short]}),
    )
    .await;
    assert_eq!(status, 400, "{e}");
    assert!(
        e["error"]["message"].as_str().unwrap().contains("225"),
        "{e}"
    );
}

/// A window session reports its own numbers (issue 56: stats said sequence 0, no variables, no
/// factors, no solves, and `/summary` was 404 while the page drew every pose): one sequence per
/// fusion batch, one solve per keyframe, the window's variables and factors, the last solve's
/// χ² and its Summary; the same after a kill -9 and the journal's replay.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_window_session_reports_its_sequence_solves_and_summary() {
    let Some(inputs) = inputs(3.0, 10) else {
        return;
    };
    let s = TestServer::start(&[]);
    let c = client();
    create_window(&c, &s).await;
    let (status, e) = get(&c, &s.url("/v1/sessions/robot/summary")).await;
    assert_eq!(status, 404, "nothing solved yet: {e}");
    let url = s.url("/v1/sessions/robot/fusion");
    let (status, reply) = post(&c, &url, &json!({"messages": [start_message(&inputs)]})).await;
    assert_eq!(status, 200, "{reply}");
    let batches = keyframe_batches(&inputs);
    for batch in &batches {
        let (status, reply) = post(&c, &url, &json!({"messages": batch})).await;
        assert_eq!(status, 200, "{reply}");
    }
    let keyframes = batches.len() as u64;
    assert!(keyframes >= 20, "{keyframes} keyframes");

    let check = |stats: &Value, summary: &Value| {
        assert_eq!(
            stats["sequence"],
            keyframes + 1,
            "start + one per batch: {stats}"
        );
        assert_eq!(stats["solved_sequence"], keyframes + 1, "{stats}");
        assert_eq!(
            stats["solves"], keyframes,
            "one solve per keyframe: {stats}"
        );
        let variables = stats["num_variables"].as_u64().unwrap();
        let factors = stats["num_factors"].as_u64().unwrap();
        // The window solves its 10 newest keyframes; the variables held fixed beside them are
        // few, and nothing grows with the keyframes that left.
        assert!((10..=40).contains(&variables), "{stats}");
        assert_eq!(summary["num_free_variables"], 10, "{summary}");
        assert!(factors >= 10, "{stats}");
        let chi2 = stats["chi2"].as_f64().unwrap();
        assert!(chi2.is_finite() && chi2 >= 0.0, "{stats}");
        assert_eq!(summary["final_chi2"].as_f64().unwrap(), chi2, "{summary}");
        assert_eq!(
            summary["num_variables"], stats["num_variables"],
            "{summary}"
        );
        assert_eq!(summary["num_factors"], stats["num_factors"], "{summary}");
        assert!(summary["iterations"].as_u64().unwrap() >= 1, "{summary}");
        (variables, factors, chi2)
    };
    let (status, stats) = get(&c, &s.url("/v1/sessions/robot")).await;
    assert_eq!(status, 200, "{stats}");
    let (status, summary) = get(&c, &s.url("/v1/sessions/robot/summary")).await;
    assert_eq!(status, 200, "{summary}");
    let before = check(&stats, &summary);
    eprintln!("window session: {stats}");

    let state_dir = s.state_dir.clone();
    s.kill();
    let s = TestServer::start_at(&state_dir, &[], &[]);
    let (stats, seconds) =
        common::server::recovered(&c, &s, "robot", std::time::Instant::now()).await;
    let (status, summary) = get(&c, &s.url("/v1/sessions/robot/summary")).await;
    assert_eq!(status, 200, "{summary}");
    let after = check(&stats, &summary);
    assert_eq!((after.0, after.1), (before.0, before.1));
    assert!(
        (after.2 - before.2).abs() <= 1e-6 * before.2.max(1e-9),
        "χ² {} after replay ({seconds:.2}s) vs {}",
        after.2,
        before.2
    );
    s.assert_no_panic();
}
