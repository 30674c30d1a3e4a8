//! The rows of docs/INPUT_CATALOGUE.md about sessions (S) and batches (B), each sent over HTTP
//! and over zenoh's rpc to a real server: the same status, code and field both ways, and the
//! session unchanged afterwards.

use crate::common;

use common::server::{client, create, get, post, recovered, zenoh_get, zenoh_peer, TestServer};
use serde_json::{json, Value};

/// One rule: what is sent where, and the error it must produce.
struct Case {
    row: &'static str,
    /// `create` (a session creation) or the session a batch goes to.
    target: &'static str,
    body: Value,
    status: u16,
    code: &'static str,
    field: Option<&'static str>,
}

fn case(
    row: &'static str,
    target: &'static str,
    body: Value,
    status: u16,
    code: &'static str,
    field: Option<&'static str>,
) -> Case {
    Case {
        row,
        target,
        body,
        status,
        code,
        field,
    }
}

fn cases() -> Vec<Case> {
    let se2 = |k: u64| json!({"key": k, "kind": "se2", "value": [0, 0, 0]});
    let between = |a: u64, b: u64| json!({"type": "between_se2", "keys": [a, b], "measurement": [1, 0, 0], "sigmas": [1, 1, 1]});
    vec![
        case(
            "S3",
            "pg",
            json!({"variable": []}),
            400,
            "invalid_field",
            Some("variable"),
        ),
        case(
            "S4",
            "pg",
            json!({"variables": [{"key": -1, "kind": "se2"}]}),
            400,
            "invalid_field",
            Some("variables[0].key"),
        ),
        case(
            "S7",
            "create",
            json!({"session": "bad name!", "kind": "pose_graph_2d"}),
            400,
            "invalid_session_name",
            Some("session"),
        ),
        case(
            "S9",
            "create",
            json!({"session": "k", "kind": "pose_graph_4d"}),
            400,
            "unknown_kind",
            Some("kind"),
        ),
        case(
            "S10",
            "create",
            json!({"session": "k", "kind": "pose_graph_2d", "options": {"max_iterations": 0}}),
            400,
            "invalid_value",
            Some("options.max_iterations"),
        ),
        case(
            "S11",
            "create",
            json!({"session": "k", "kind": "pose_graph_2d", "options": {"function_tolerance": -1.0}}),
            400,
            "invalid_value",
            Some("options.function_tolerance"),
        ),
        case(
            "S12",
            "create",
            json!({"session": "k", "kind": "pose_graph_2d", "options": {"initial_lambda": 0.0}}),
            400,
            "invalid_value",
            Some("options.initial_lambda"),
        ),
        case(
            "S148",
            "create",
            json!({"session": "k", "kind": "bundle_adjustment", "options": {"threads": 257}}),
            400,
            "invalid_value",
            Some("options.threads"),
        ),
        case(
            "S13",
            "create",
            json!({"session": "k", "kind": "pose_graph_2d", "options": {"method": "newton"}}),
            400,
            "invalid_field",
            Some("options.method"),
        ),
        case(
            "S14",
            "create",
            json!({"session": "k", "kind": "pose_graph_2d", "auto_optimize": {"policy": "every_n_factors", "factors": 0}}),
            400,
            "invalid_value",
            Some("auto_optimize.factors"),
        ),
        case("S6", "nobody", json!({}), 404, "unknown_session", None),
        case(
            "B1",
            "window",
            json!({"variables": [se2(5)]}),
            400,
            "wrong_kind",
            Some("session"),
        ),
        case(
            "B2",
            "pg",
            json!({"variables": [{"key": 5, "kind": "se3", "value": [0, 0, 0, 0, 0, 0, 1]}]}),
            400,
            "wrong_kind",
            Some("variables[0].kind"),
        ),
        case(
            "B3",
            "pg",
            json!({"variables": [se2(0)]}),
            422,
            "duplicate_variable",
            Some("variables[0].key"),
        ),
        case(
            "B3",
            "pg",
            json!({"variables": [se2(7), se2(7)]}),
            422,
            "duplicate_variable",
            Some("variables[1].key"),
        ),
        case(
            "B4",
            "pg",
            json!({"variables": [{"key": 5, "kind": "se2", "value": [0, 0]}]}),
            400,
            "wrong_dimension",
            Some("variables[0].value"),
        ),
        case(
            "B5",
            "pg3",
            json!({"variables": [{"key": 5, "kind": "se3", "value": [0, 0, 0, 0, 0, 0, 2]}]}),
            400,
            "invalid_value",
            Some("variables[0].value"),
        ),
        case(
            "B7",
            "pg",
            json!({"factors": [{"type": "between_se3", "keys": [0, 1], "measurement": [0, 0, 0, 0, 0, 0, 1], "sigmas": [1, 1, 1, 1, 1, 1]}]}),
            400,
            "unknown_factor_type",
            Some("factors[0].type"),
        ),
        case(
            "B8",
            "pg",
            json!({"factors": [{"type": "between_se2", "keys": [0], "measurement": [1, 0, 0], "sigmas": [1, 1, 1]}]}),
            400,
            "wrong_dimension",
            Some("factors[0].keys"),
        ),
        case(
            "B9",
            "pg",
            json!({"factors": [between(1, 1)]}),
            400,
            "repeated_variable",
            Some("factors[0].keys[1]"),
        ),
        case(
            "B10",
            "pg",
            json!({"factors": [between(0, 99)]}),
            422,
            "unknown_variable",
            Some("factors[0].keys[1]"),
        ),
        case(
            "B11",
            "ba",
            json!({"factors": [{"type": "reprojection_snavely", "keys": [1000, 1], "measurement": [1, 2], "sigmas": [1, 1]}]}),
            422,
            "wrong_kind",
            Some("factors[0].keys[0]"),
        ),
        case(
            "B12",
            "pg",
            json!({"factors": [{"type": "between_se2", "keys": [0, 1], "measurement": [1, 0], "sigmas": [1, 1, 1]}]}),
            400,
            "wrong_dimension",
            Some("factors[0].measurement"),
        ),
        case(
            "B13",
            "pg",
            json!({"factors": [{"type": "between_se2", "keys": [0, 1], "measurement": [1, 0, 0]}]}),
            400,
            "missing_noise",
            Some("factors[0]"),
        ),
        case(
            "B14",
            "pg",
            json!({"factors": [{"type": "between_se2", "keys": [0, 1], "measurement": [1, 0, 0], "information": [1, 0, 1]}]}),
            400,
            "wrong_dimension",
            Some("factors[0].information"),
        ),
        case(
            "B15",
            "pg",
            json!({"factors": [{"type": "between_se2", "keys": [0, 1], "measurement": [1, 0, 0], "information": [1, 0.5, 0, 0, 1, 0, 0, 0, 1]}]}),
            400,
            "bad_information",
            Some("factors[0].information"),
        ),
        case(
            "B16",
            "pg",
            json!({"factors": [{"type": "between_se2", "keys": [0, 1], "measurement": [1, 0, 0], "information": [1, 0, 0, -1, 0, 1]}]}),
            400,
            "bad_information",
            Some("factors[0].information"),
        ),
        case(
            "B17",
            "pg",
            json!({"factors": [{"type": "between_se2", "keys": [0, 1], "measurement": [1, 0, 0], "sigmas": [1, 1]}]}),
            400,
            "wrong_dimension",
            Some("factors[0].sigmas"),
        ),
        case(
            "B18",
            "pg",
            json!({"factors": [{"type": "between_se2", "keys": [0, 1], "measurement": [1, 0, 0], "sigmas": [1, 0, 1]}]}),
            400,
            "bad_information",
            Some("factors[0].sigmas[1]"),
        ),
        case(
            "B20",
            "pg",
            json!({"factors": [{"type": "between_se2", "keys": [0, 1], "measurement": [1, 0, 0], "sigmas": [1, 1, 1], "robust": {"kind": "huber", "scale": -1.0}}]}),
            400,
            "invalid_value",
            Some("factors[0].robust.scale"),
        ),
        case(
            "B21",
            "pg",
            json!({"variables": [{"key": 50, "kind": "se2"}]}),
            422,
            "missing_value",
            Some("variables[0].value"),
        ),
        case(
            "B22",
            "pg",
            json!({"remove_factors": [12345]}),
            422,
            "unknown_factor",
            Some("remove_factors[0]"),
        ),
        case(
            "B23",
            "pg",
            json!({"fix": [77]}),
            422,
            "unknown_variable",
            Some("fix[0]"),
        ),
        case(
            "B23",
            "pg",
            json!({"unfix": [77]}),
            422,
            "unknown_variable",
            Some("unfix[0]"),
        ),
        case(
            "B24",
            "pg",
            json!({"fix": [1], "unfix": [1]}),
            400,
            "conflicting_fix",
            Some("unfix[0]"),
        ),
        case(
            "B25",
            "pg",
            json!({"guesses": [{"key": 77, "value": [0, 0, 0]}]}),
            422,
            "unknown_variable",
            Some("guesses[0].key"),
        ),
        case(
            "B26",
            "pg",
            json!({"guesses": [{"key": 1, "value": [0, 0]}]}),
            400,
            "wrong_dimension",
            Some("guesses[0].value"),
        ),
        // 1/σ² overflows: the field names `information` although `sigmas` was sent.
        case(
            "B19",
            "pg",
            json!({"factors": [{"type": "between_se2", "keys": [0, 1], "measurement": [1, 0, 0], "sigmas": [1e-200, 1, 1]}]}),
            400,
            "bad_information",
            Some("factors[0].information"),
        ),
        case(
            "B27",
            "ba",
            json!({"variables": [{"key": 2000, "kind": "point3", "value": [0, 0, 0]}],
            "factors": [{"type": "reprojection_snavely", "keys": [1, 2000], "measurement": [1, 2], "sigmas": [1, 1]}]}),
            422,
            "non_finite_residual",
            Some("factors[0]"),
        ),
    ]
}

#[tokio::test(flavor = "multi_thread")]
async fn every_session_and_batch_rule_answers_the_same_over_http_and_zenoh() {
    let s = TestServer::start(&[]);
    let c = client();
    let setup = [
        (
            "pg",
            "pose_graph_2d",
            json!({"variables": [{"key": 0, "kind": "se2", "value": [0, 0, 0]}, {"key": 1, "kind": "se2", "value": [1, 0, 0]}],
            "factors": [{"type": "between_se2", "keys": [0, 1], "measurement": [1, 0, 0], "sigmas": [1, 1, 1]}]}),
        ),
        (
            "pg3",
            "pose_graph_3d",
            json!({"variables": [{"key": 0, "kind": "se3", "value": [0, 0, 0, 0, 0, 0, 1]}]}),
        ),
        // A camera at the origin (key 1) and a point in front of it (key 1000).
        (
            "ba",
            "bundle_adjustment",
            json!({"variables": [{"key": 1, "kind": "snavely_camera", "value": [0, 0, 0, 0, 0, 0, 500, 0, 0]},
            {"key": 1000, "kind": "point3", "value": [0, 0, -5]}]}),
        ),
        ("window", "sliding_window", Value::Null),
    ];
    for (name, kind, batch) in &setup {
        create(
            &c,
            &s,
            &json!({"session": name, "kind": kind, "auto_optimize": {"policy": "manual"}}),
        )
        .await;
        if !batch.is_null() {
            let (status, v) =
                post(&c, &s.url(&format!("/v1/sessions/{name}/batches")), batch).await;
            assert_eq!(status, 200, "{v}");
        }
    }
    let z = zenoh_peer(&s.zenoh).await;
    let mut checked = Vec::new();
    for case in cases() {
        let (url, command) = if case.target == "create" {
            let mut command = case.body.clone();
            command["op"] = json!("create_session");
            (s.url("/v1/sessions"), command)
        } else {
            (
                s.url(&format!("/v1/sessions/{}/batches", case.target)),
                json!({"op": "apply_batch", "session": case.target, "batch": case.body}),
            )
        };
        let before = if case.target == "create" || case.target == "nobody" {
            Value::Null
        } else {
            get(&c, &s.url(&format!("/v1/sessions/{}", case.target)))
                .await
                .1
        };
        let (status, http) = post(&c, &url, &case.body).await;
        let what = format!("{} {}", case.row, case.body);
        assert_eq!(status, case.status, "HTTP {what}: {http}");
        assert_eq!(http["error"]["code"], case.code, "HTTP {what}: {http}");
        assert_eq!(
            http["error"]["field"].as_str(),
            case.field,
            "HTTP {what}: {http}"
        );
        let zenoh = zenoh_get(&z, "factord/rpc", Some(&command))
            .await
            .expect_err(&what);
        assert_eq!(
            zenoh["error"]["status"], case.status,
            "zenoh {what}: {zenoh}"
        );
        assert_eq!(zenoh["error"]["code"], case.code, "zenoh {what}: {zenoh}");
        // The rpc wraps the batch in a command: a serde path starts one level deeper.
        let zenoh_field = zenoh["error"]["field"]
            .as_str()
            .map(|f| f.trim_start_matches("batch.").to_string());
        assert_eq!(zenoh_field.as_deref(), case.field, "zenoh {what}: {zenoh}");
        if !before.is_null() {
            let after = get(&c, &s.url(&format!("/v1/sessions/{}", case.target)))
                .await
                .1;
            assert_eq!(
                (
                    after["sequence"].clone(),
                    after["num_variables"].clone(),
                    after["num_factors"].clone()
                ),
                (
                    before["sequence"].clone(),
                    before["num_variables"].clone(),
                    before["num_factors"].clone()
                ),
                "{what} changed the session"
            );
        }
        checked.push(case.row);
    }
    println!("rows checked over HTTP and zenoh: {checked:?}");
    z.close().await.unwrap();
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn auto_optimize_policies_refuse_fields_they_do_not_have() {
    let s = TestServer::start(&["--no-zenoh"]);
    let c = client();
    for policy in [
        json!({"policy": "manual", "bogus": 1}),
        json!({"policy": "every_batch", "factors": 3}),
    ] {
        let (status, v) = post(
            &c,
            &s.url("/v1/sessions"),
            &json!({"kind": "pose_graph_2d", "auto_optimize": policy}),
        )
        .await;
        assert_eq!(status, 400, "{policy}: {v}");
        assert_eq!(v["error"]["code"], "invalid_field");
    }
    let v = create(
        &c,
        &s,
        &json!({"session": "p", "kind": "pose_graph_2d", "auto_optimize": {"policy": "manual"}}),
    )
    .await;
    assert_eq!(v["auto_optimize"], json!({"policy": "manual"}));
}

/// Errors axum's extractors raise themselves come back in the same JSON shape as ours.
#[tokio::test(flavor = "multi_thread")]
async fn extractor_errors_are_json_too() {
    let s = TestServer::start(&["--no-zenoh"]);
    let c = client();
    create(&c, &s, &json!({"session": "w", "kind": "pose_graph_2d"})).await;
    for path in [
        "/v1/sessions/%FF",
        "/v1/sessions/%FF/estimate",
        "/v1/sessions/w/ws",
    ] {
        let response = c.get(s.url(path)).send().await.unwrap();
        let status = response.status().as_u16();
        let content_type = response.headers()["content-type"]
            .to_str()
            .unwrap()
            .to_string();
        let v: Value = response.json().await.unwrap_or(Value::Null);
        assert!((400..500).contains(&status), "{path}: {status}");
        assert!(
            content_type.starts_with("application/json"),
            "{path}: {content_type}"
        );
        assert_eq!(v["error"]["code"], "invalid_request", "{path}: {v}");
        assert_eq!(v["error"]["status"], status, "{path}: {v}");
    }
    s.assert_no_panic();
}

fn start(overrides: Value) -> Value {
    let mut m = json!({"type": "start", "t": 0.0, "position": [0, 0, 0], "rotation_xyzw": [0, 0, 0, 1],
        "sigmas": {"position": 0.01, "rotation": 0.01, "velocity": 0.1, "accel_bias": 0.1, "gyro_bias": 0.01}});
    for (k, v) in overrides.as_object().unwrap() {
        m[k] = v.clone();
    }
    m
}

fn imu(t: f64) -> Value {
    json!({"type": "imu", "t": t, "accel": [0, 0, 9.81], "gyro": [0, 0, 0]})
}

fn preintegrated(delta_t: f64, covariance: Vec<f64>) -> Value {
    let eye = [1, 0, 0, 0, 1, 0, 0, 0, 1];
    json!({"type": "preintegrated_keyframe", "t": 0.5, "delta_t": delta_t,
        "delta_rotation_xyzw": [0, 0, 0, 1], "delta_velocity": [0, 0, 0], "delta_position": [0, 0, 0],
        "accel_bias": [0, 0, 0], "gyro_bias": [0, 0, 0],
        "d_rotation_d_gyro_bias": eye, "d_velocity_d_accel_bias": eye, "d_velocity_d_gyro_bias": eye,
        "d_position_d_accel_bias": eye, "d_position_d_gyro_bias": eye, "covariance": covariance})
}

/// The fusion rows (F): each message alone, over HTTP and zenoh rpc; nothing it touches changes.
#[tokio::test(flavor = "multi_thread")]
async fn every_fusion_rule_answers_the_same_over_http_and_zenoh() {
    let s = TestServer::start(&[]);
    let c = client();
    let identity_cov: Vec<f64> = (0..225)
        .map(|i| if i % 16 == 0 { 1e-4 } else { 0.0 })
        .collect();
    // `win`: keyframes 0 (t 0) and 1 (t 0.01), then a sample at 0.015; `bare`: started, no
    // samples; `fresh`: not started; `pg`: not a window.
    let setup: [(&str, &str, Vec<Value>); 4] = [
        (
            "win",
            "sliding_window",
            vec![
                start(json!({})),
                imu(0.005),
                imu(0.01),
                json!({"type": "keyframe", "t": 0.01}),
                imu(0.015),
            ],
        ),
        ("bare", "sliding_window", vec![start(json!({}))]),
        ("fresh", "sliding_window", vec![]),
        ("pg", "pose_graph_2d", vec![]),
    ];
    for (name, kind, messages) in &setup {
        create(&c, &s, &json!({"session": name, "kind": kind})).await;
        if !messages.is_empty() {
            let (status, v) = post(
                &c,
                &s.url(&format!("/v1/sessions/{name}/fusion")),
                &json!({"messages": messages}),
            )
            .await;
            assert_eq!(status, 200, "{v}");
        }
    }
    let rel = |from: u64, to: u64, sigma: f64| {
        json!({"type": "relative_pose", "from": from, "to": to,
        "position": [0.01, 0, 0], "rotation_xyzw": [0, 0, 0, 1], "sigma_position": sigma, "sigma_rotation": 0.01})
    };
    let cases: Vec<(&str, &str, Value, u16, &str)> = vec![
        ("F1", "pg", imu(0.1), 400, "wrong_kind"),
        ("F2", "fresh", imu(0.1), 400, "invalid_message"),
        ("F3", "win", start(json!({})), 400, "invalid_message"),
        (
            "F4",
            "fresh",
            start(
                json!({"sigmas": {"position": 0, "rotation": 0.01, "velocity": 0.1, "accel_bias": 0.1, "gyro_bias": 0.01}}),
            ),
            400,
            "invalid_message",
        ),
        (
            "F5",
            "fresh",
            start(json!({"window": 1})),
            400,
            "invalid_message",
        ),
        (
            "F6",
            "fresh",
            start(json!({"gravity": -9.81})),
            400,
            "invalid_message",
        ),
        (
            "F7",
            "fresh",
            start(
                json!({"imu_noise": {"accel_noise_density": 0, "gyro_noise_density": 1e-4, "accel_random_walk": 1e-3, "gyro_random_walk": 1e-5}}),
            ),
            400,
            "invalid_message",
        ),
        ("F8", "win", imu(0.005), 422, "rejected_message"),
        ("F9", "win", imu(0.015), 422, "rejected_message"),
        (
            "F10",
            "win",
            json!({"type": "keyframe", "t": 0.01}),
            422,
            "rejected_message",
        ),
        (
            "F11",
            "bare",
            json!({"type": "keyframe", "t": 0.1}),
            422,
            "rejected_message",
        ),
        (
            "F12",
            "win",
            json!({"type": "keyframe", "t": 0.012}),
            422,
            "rejected_message",
        ),
        (
            "F13",
            "bare",
            preintegrated(0.5, vec![1.0, 0.0, 1.0]),
            400,
            "invalid_message",
        ),
        (
            "F14",
            "bare",
            preintegrated(0.25, identity_cov.clone()),
            400,
            "invalid_message",
        ),
        (
            "F15",
            "bare",
            preintegrated(0.5, vec![0.0; 225]),
            400,
            "invalid_message",
        ),
        ("F16", "win", rel(0, 1, 0.0), 400, "invalid_message"),
        (
            "F17",
            "win",
            json!({"type": "position_prior", "key": 99, "position": [0, 0, 0], "sigma": 0.1}),
            422,
            "rejected_message",
        ),
        ("F18", "win", rel(1, 1, 0.02), 422, "rejected_message"),
        (
            "F24",
            "win",
            json!({"type": "relative_pose", "from": 0, "to": 1, "position": [0.01, 0, 0],
                "rotation_xyzw": [0, 0, 0, 0], "sigma_position": 0.01, "sigma_rotation": 0.01}),
            400,
            "invalid_message",
        ),
        (
            "F20",
            "win",
            json!({"type": "position_prior", "key": 1, "position": [0, 0, 0], "sigma": 1e-200}),
            422,
            "rejected_message",
        ),
        (
            "F22",
            "win",
            json!({"type": "teleport", "t": 1.0}),
            400,
            "invalid_field",
        ),
    ];
    let z = zenoh_peer(&s.zenoh).await;
    for (row, session, message, status, code) in cases {
        let what = format!("{row} {message}");
        let field = match row {
            "F1" => "session",
            "F22" => "messages[0].type",
            _ => "messages[0]",
        };
        let before = get(&c, &s.url(&format!("/v1/sessions/{session}/graph")))
            .await
            .1;
        let (got, http) = post(
            &c,
            &s.url(&format!("/v1/sessions/{session}/fusion")),
            &json!({"messages": [message.clone()]}),
        )
        .await;
        assert_eq!(
            (got, http["error"]["code"].as_str()),
            (status, Some(code)),
            "HTTP {what}: {http}"
        );
        assert_eq!(http["error"]["field"], field, "HTTP {what}: {http}");
        let command = json!({"op": "fusion", "session": session, "messages": [message]});
        let zenoh = zenoh_get(&z, "factord/rpc", Some(&command))
            .await
            .expect_err(&what);
        assert_eq!(
            (
                zenoh["error"]["status"].as_u64(),
                zenoh["error"]["code"].as_str()
            ),
            (Some(status as u64), Some(code)),
            "zenoh {what}: {zenoh}"
        );
        assert_eq!(zenoh["error"]["field"], field, "zenoh {what}: {zenoh}");
        let after = get(&c, &s.url(&format!("/v1/sessions/{session}/graph")))
            .await
            .1;
        assert_eq!(before["poses"], after["poses"], "{what} changed the window");
    }
    z.close().await.unwrap();
    s.assert_no_panic();
}

/// F21: a window whose solve cannot start (a prior 1e300 away from the pose it pins makes the
/// cost overflow) answers 422 solve_failed at the next keyframe, over HTTP and rpc. The keyframe
/// stays applied, as a batch stays accepted when a session's solve fails (S22).
#[tokio::test(flavor = "multi_thread")]
async fn a_window_solve_that_fails_is_422_solve_failed_over_http_and_zenoh() {
    let s = TestServer::start(&[]);
    let c = client();
    let cov: Vec<f64> = (0..225)
        .map(|i| if i % 16 == 0 { 1e-4 } else { 0.0 })
        .collect();
    let keyframe = |t: f64, dx: f64| {
        let mut m = preintegrated(0.5, cov.clone());
        m["t"] = json!(t);
        m["delta_position"] = json!([dx, 0, 0]);
        m
    };
    create(&c, &s, &json!({"session": "far", "kind": "sliding_window"})).await;
    // The prior comes after the keyframe's solve: a keyframe optimises the window, a prior
    // alone does not.
    for messages in [
        json!([start(json!({})), keyframe(0.5, 1e300)]),
        json!([{"type": "position_prior", "key": 1, "position": [0, 0, 0], "sigma": 0.001}]),
    ] {
        let url = s.url("/v1/sessions/far/fusion");
        let (status, v) = post(&c, &url, &json!({ "messages": messages })).await;
        assert_eq!(status, 200, "{v}");
    }
    let poses = |graph: &Value| graph["poses"].as_array().map_or(0, Vec::len);
    let z = zenoh_peer(&s.zenoh).await;
    for (attempt, t) in [(0, 1.0), (1, 1.5)] {
        let before = poses(&get(&c, &s.url("/v1/sessions/far/graph")).await.1);
        let messages = json!([keyframe(t, 0.0)]);
        let v = if attempt == 0 {
            let (status, v) = post(
                &c,
                &s.url("/v1/sessions/far/fusion"),
                &json!({ "messages": messages }),
            )
            .await;
            assert_eq!(status, 422, "HTTP F21: {v}");
            v
        } else {
            let command = json!({"op": "fusion", "session": "far", "messages": messages});
            zenoh_get(&z, "factord/rpc", Some(&command))
                .await
                .expect_err("rpc F21")
        };
        assert_eq!(v["error"]["status"], 422, "F21: {v}");
        assert_eq!(v["error"]["code"], "solve_failed", "F21: {v}");
        assert_eq!(v["error"]["field"], "messages", "F21: {v}");
        assert!(
            v["error"]["message"]
                .as_str()
                .is_some_and(|m| m.contains("stay applied")),
            "{v}"
        );
        let after = poses(&get(&c, &s.url("/v1/sessions/far/graph")).await.1);
        assert_eq!(after, before + 1, "the keyframe stays in the window");
    }
    // The journal holds what stayed applied, and its replay expects the same failed solves.
    z.close().await.unwrap();
    let graph = get(&c, &s.url("/v1/sessions/far/graph")).await.1;
    let state_dir = s.state_dir.clone();
    s.kill();
    let s = TestServer::start_at(&state_dir, &[], &[]);
    recovered(&c, &s, "far", std::time::Instant::now()).await;
    let after = get(&c, &s.url("/v1/sessions/far/graph")).await.1;
    assert_eq!(after["poses"], graph["poses"], "after a restart");
    println!("rows checked over HTTP and rpc: F21 (and its journal replay)");
    s.assert_no_panic();
}
