//! The smaller holes of issue 14 (item 10), each over the wire: an overflowing cost, an endless
//! window, an inexact float key, unnamed sessions after a restart, and marginal factorisations
//! counted in `memory_bytes`. Then those of issue 52 (item 12): robust scales out of range,
//! internal factor names as user types, far-off quaternions, unnamed sessions after a named `s1`.

use crate::common;

use common::server::{client, create, g2o_batches, get, post, TestServer};
use serde_json::{json, Value};

#[tokio::test(flavor = "multi_thread")]
async fn a_factor_whose_weighted_cost_overflows_is_refused() {
    let s = TestServer::start(&["--no-zenoh", "--no-journal"]);
    let c = client();
    create(&c, &s, &json!({"session": "p", "kind": "pose_graph_2d"})).await;
    // The residual (1e155) is finite; its square is not.
    let batch = json!({
        "variables": [{"key": 0, "kind": "se2", "value": [0, 0, 0]}],
        "factors": [{"type": "prior_se2", "keys": [0], "measurement": [1e155, 0, 0],
                     "information": [1, 0, 0, 1, 0, 1]}]});
    let (status, v) = post(&c, &s.url("/v1/sessions/p/batches"), &batch).await;
    assert_eq!(status, 422, "{v}");
    assert_eq!(v["error"]["code"], "non_finite_residual", "{v}");
    assert_eq!(v["error"]["field"], "factors[0]", "{v}");
    let (_, stats) = get(&c, &s.url("/v1/sessions/p")).await;
    assert_eq!(
        stats["num_variables"], 0,
        "nothing of the batch applied: {stats}"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn integer_fields_refuse_floats_that_cannot_be_exact() {
    let s = TestServer::start(&["--no-zenoh", "--no-journal"]);
    let c = client();
    create(&c, &s, &json!({"session": "k", "kind": "pose_graph_2d"})).await;
    // 2^53 + 1 written as a float reads as 2^53: which key was meant cannot be told.
    let text = r#"{"variables": [{"key": 9007199254740993.0, "kind": "se2", "value": [0, 0, 0]}]}"#;
    let r = c
        .post(s.url("/v1/sessions/k/batches"))
        .header("content-type", "application/json")
        .body(text)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 400);
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["error"]["field"], "variables[0].key", "{v}");
    // Written as an integer, the same key is exact and accepted.
    let exact = r#"{"variables": [{"key": 9007199254740993, "kind": "se2", "value": [0, 0, 0]}]}"#;
    let r = c
        .post(s.url("/v1/sessions/k/batches"))
        .header("content-type", "application/json")
        .body(exact)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 200);
}

#[tokio::test(flavor = "multi_thread")]
async fn a_window_beyond_its_maximum_is_refused() {
    let s = TestServer::start(&["--no-zenoh", "--no-journal"]);
    let c = client();
    create(&c, &s, &json!({"session": "w", "kind": "sliding_window"})).await;
    let start = |window: Value| {
        json!({"messages": [{"type": "start", "t": 0.0, "position": [0, 0, 0],
            "rotation_xyzw": [0, 0, 0, 1], "window": window,
            "sigmas": {"position": 0.1, "rotation": 0.1, "velocity": 0.1,
                       "accel_bias": 0.1, "gyro_bias": 0.1}}]})
    };
    let url = s.url("/v1/sessions/w/fusion");
    let (status, v) = post(&c, &url, &start(json!(18446744073709551615u64))).await;
    assert_eq!(status, 400, "{v}");
    assert_eq!(v["error"]["code"], "invalid_message", "{v}");
    assert_eq!(v["error"]["field"], "messages[0]", "{v}");
    let (status, v) = post(&c, &url, &start(json!(1001))).await;
    assert_eq!(status, 400, "{v}");
    let (status, v) = post(&c, &url, &start(json!(1000))).await;
    assert_eq!(status, 200, "the largest window is accepted: {v}");
}

#[tokio::test(flavor = "multi_thread")]
async fn unnamed_sessions_after_a_restart_take_fresh_names() {
    let dir = common::temp_dir("unnamed");
    let c = client();
    let s = TestServer::start_at(&dir, &["--no-zenoh"], &[]);
    for expected in ["s1", "s2"] {
        let v = create(&c, &s, &json!({"kind": "pose_graph_2d"})).await;
        assert_eq!(v["session"], expected, "{v}");
    }
    s.kill();
    // A directory that cannot be loaded keeps its name too (it is never overwritten).
    let unloadable = dir.join("sessions/s7");
    std::fs::create_dir_all(&unloadable).unwrap();
    std::fs::write(unloadable.join("session.json"), "not json").unwrap();
    let s = TestServer::start_at(&dir, &["--no-zenoh"], &[]);
    let v = create(&c, &s, &json!({"kind": "pose_graph_2d"})).await;
    assert_eq!(v["session"], "s8", "{v}");
}

#[tokio::test(flavor = "multi_thread")]
async fn marginal_factorisations_count_in_memory_bytes() {
    let s = TestServer::start(&["--no-zenoh", "--no-journal"]);
    let c = client();
    create(&c, &s, &json!({"session": "m", "kind": "pose_graph_2d"})).await;
    let (mut variables, mut factors) = (Vec::new(), Vec::new());
    for b in g2o_batches(&common::synthetic_manhattan(3000, 3)) {
        variables.extend(b["variables"].as_array().unwrap().clone());
        factors.extend(b["factors"].as_array().unwrap().clone());
    }
    let all = json!({"variables": variables, "factors": factors});
    let (status, v) = post(&c, &s.url("/v1/sessions/m/batches?wait=true"), &all).await;
    assert_eq!(status, 200, "{v}");
    let (_, before) = get(&c, &s.url("/v1/sessions/m")).await;
    let (status, v) = get(&c, &s.url("/v1/sessions/m/marginals?keys=1500")).await;
    assert_eq!(status, 200, "{v}");
    let (_, after) = get(&c, &s.url("/v1/sessions/m")).await;
    let grown = after["memory_bytes"].as_u64().unwrap() - before["memory_bytes"].as_u64().unwrap();
    // The factor of 3000 SE(2) poses holds at least its 9000 diagonal entries.
    assert!(
        grown >= 8 * 9000,
        "memory_bytes grew {grown} bytes: {before} → {after}"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn robust_scales_out_of_range_are_refused() {
    let s = TestServer::start(&["--no-zenoh", "--no-journal"]);
    let c = client();
    create(&c, &s, &json!({"session": "r", "kind": "pose_graph_2d"})).await;
    let batch = |kind: &str, scale: f64| {
        // A new variable each time: the key is the scale's exponent, made non-negative.
        let key = (scale.log10().round() + 400.0) as u64;
        json!({"variables": [{"key": key, "kind": "se2", "value": [0, 0, 0]}],
               "factors": [{"type": "prior_se2", "keys": [key], "measurement": [1, 0, 0],
                            "sigmas": [1, 1, 1], "robust": {"kind": kind, "scale": scale}}]})
    };
    let url = s.url("/v1/sessions/r/batches?wait=true");
    for (kind, scale) in [
        ("tukey", 1e300),
        ("cauchy", 1e-300),
        ("huber", 2e9),
        ("huber", 1e-10),
    ] {
        let (status, v) = post(&c, &url, &batch(kind, scale)).await;
        assert_eq!(status, 400, "{kind} {scale}: {v}");
        assert_eq!(v["error"]["code"], "invalid_value", "{v}");
        assert_eq!(v["error"]["field"], "factors[0].robust.scale", "{v}");
    }
    let (_, stats) = get(&c, &s.url("/v1/sessions/r")).await;
    assert_eq!(stats["num_variables"], 0, "nothing applied: {stats}");
    let (status, v) = post(&c, &url, &batch("cauchy", 1e-9)).await;
    assert_eq!(status, 200, "the smallest scale is accepted: {v}");
    let (status, v) = post(&c, &url, &batch("tukey", 1e9)).await;
    assert_eq!(status, 200, "the largest scale is accepted: {v}");
}

#[tokio::test(flavor = "multi_thread")]
async fn internal_factor_names_are_refused_as_user_type_names() {
    let s = TestServer::start(&["--no-zenoh", "--no-journal"]);
    let c = client();
    let names = [
        "imu_preintegration",
        "prior_nav",
        "pose_prior_nav",
        "position_prior_nav",
        "relative_pose_nav",
        "marginal_prior",
        "photometric_patch",
    ];
    for name in names {
        let mut ty = common::user_between_se2();
        ty["name"] = json!(name);
        let body = json!({"session": "u", "kind": "pose_graph_2d",
                          "factor_types": [common::user_between_se2(), ty]});
        let (status, v) = post(&c, &s.url("/v1/sessions"), &body).await;
        assert_eq!(status, 400, "{name}: {v}");
        assert_eq!(v["error"]["code"], "invalid_factor_type", "{v}");
        assert_eq!(v["error"]["field"], "factor_types[1].name", "{v}");
    }
    let body = json!({"session": "u", "kind": "pose_graph_2d",
                      "factor_types": [common::user_between_se2()]});
    create(&c, &s, &body).await;
}

#[tokio::test(flavor = "multi_thread")]
async fn quaternions_far_from_unit_norm_are_refused() {
    let s = TestServer::start(&["--no-zenoh", "--no-journal"]);
    let c = client();
    create(&c, &s, &json!({"session": "q", "kind": "sliding_window"})).await;
    let start = |q: Value| {
        json!({"messages": [{"type": "start", "t": 0.0, "position": [0, 0, 0],
            "rotation_xyzw": q,
            "sigmas": {"position": 0.1, "rotation": 0.1, "velocity": 0.1,
                       "accel_bias": 0.1, "gyro_bias": 0.1}}]})
    };
    let url = s.url("/v1/sessions/q/fusion");
    for q in [
        json!([0, 0, 0, 1e-160]),
        json!([0, 0, 0, 0]),
        json!([0, 0, 0, 2]),
    ] {
        let (status, v) = post(&c, &url, &start(q.clone())).await;
        assert_eq!(status, 400, "{q}: {v}");
        assert_eq!(v["error"]["code"], "invalid_message", "{v}");
        assert_eq!(v["error"]["field"], "messages[0]", "{v}");
        let message = v["error"]["message"].as_str().unwrap();
        assert!(message.contains("rotation_xyzw"), "{v}");
    }
    // Rounded output (norm 1.00004) is accepted and stored normalised.
    let (status, v) = post(&c, &url, &start(json!([0.0006, 0.0011, 0.0038, 1.00004]))).await;
    assert_eq!(status, 200, "{v}");
    let q = v["latest"]["rotation_xyzw"]
        .as_array()
        .expect("the state after start");
    let norm: f64 = q
        .iter()
        .map(|x| x.as_f64().unwrap().powi(2))
        .sum::<f64>()
        .sqrt();
    assert!((norm - 1.0).abs() < 1e-12, "{v}");
    // A relative pose's quaternion too.
    let relative = json!({"messages": [{"type": "relative_pose", "from": 0, "to": 0,
        "position": [0, 0, 0], "rotation_xyzw": [0, 0, 1e-160, 0],
        "sigma_position": 0.1, "sigma_rotation": 0.1}]});
    let (status, v) = post(&c, &url, &relative).await;
    assert_eq!(status, 400, "{v}");
    assert!(
        v["error"]["message"]
            .as_str()
            .unwrap()
            .contains("rotation_xyzw"),
        "{v}"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn unnamed_creation_skips_names_clients_took() {
    let dir = common::temp_dir("unnamed-skip");
    let c = client();
    let s = TestServer::start_at(&dir, &["--no-zenoh"], &[]);
    create(&c, &s, &json!({"session": "s1", "kind": "pose_graph_2d"})).await;
    create(&c, &s, &json!({"session": "s2", "kind": "pose_graph_2d"})).await;
    let v = create(&c, &s, &json!({"kind": "pose_graph_2d"})).await;
    assert_eq!(v["session"], "s3", "{v}");
    let s = TestServer::start(&["--no-zenoh", "--no-journal"]);
    create(&c, &s, &json!({"session": "s1", "kind": "pose_graph_2d"})).await;
    let v = create(&c, &s, &json!({"kind": "pose_graph_2d"})).await;
    assert_eq!(v["session"], "s2", "{v}");
}

#[tokio::test(flavor = "multi_thread")]
async fn distinct_producers_beyond_the_limit_are_refused() {
    let config = common::temp_dir("producers").join("config.json");
    std::fs::write(
        &config,
        json!({"limits": {"max_producers_per_session": 3}}).to_string(),
    )
    .unwrap();
    let s = TestServer::start(&[
        "--no-zenoh",
        "--no-journal",
        "--config",
        config.to_str().unwrap(),
    ]);
    let c = client();
    create(&c, &s, &json!({"session": "p", "kind": "pose_graph_2d"})).await;
    let url = s.url("/v1/sessions/p/batches");
    let batch = |producer: &str, seq: u64, key: u64| {
        json!({"producer": producer, "producer_seq": seq,
               "variables": [{"key": key, "kind": "se2", "value": [0, 0, 0]}]})
    };
    for (k, producer) in ["a", "b", "c"].into_iter().enumerate() {
        let (status, v) = post(&c, &url, &batch(producer, 1, k as u64)).await;
        assert_eq!(status, 200, "{v}");
    }
    let (status, v) = post(&c, &url, &batch("d", 1, 9)).await;
    assert_eq!(status, 422, "{v}");
    assert_eq!(v["error"]["code"], "too_many_producers", "{v}");
    assert_eq!(v["error"]["field"], "producer", "{v}");
    // Producers already counted go on.
    let (status, v) = post(&c, &url, &batch("a", 2, 10)).await;
    assert_eq!(status, 200, "{v}");
    let (_, stats) = get(&c, &s.url("/v1/sessions/p")).await;
    assert_eq!(
        stats["num_variables"], 4,
        "the refused batch applied nothing: {stats}"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn the_documented_expression_depth_is_the_real_one() {
    let s = TestServer::start(&["--no-zenoh", "--no-journal"]);
    let c = client();
    // translation(inverse^k(between(z, between(a, b)))): its leaves `a`, `b` are k + 3 deep.
    let typed = |k: usize| {
        let mut e = json!({"between": ["z", {"between": ["a", "b"]}]});
        for _ in 0..k {
            e = json!({"inverse": [e]});
        }
        let mut ty = common::user_between_se2();
        ty["residual"] = json!({"translation": [e]});
        ty
    };
    // One deeper than the maximum (48): the depth rule's error, not malformed_json.
    let body = json!({"session": "d", "kind": "pose_graph_2d", "factor_types": [typed(46)]});
    let (status, v) = post(&c, &s.url("/v1/sessions"), &body).await;
    assert_eq!(status, 400, "{v}");
    assert_eq!(v["error"]["code"], "invalid_factor_type", "{v}");
    let field = v["error"]["field"].as_str().unwrap();
    let deep = format!(
        "factor_types[0].residual.translation[0]{}",
        ".inverse[0]".repeat(46)
    );
    assert!(field.starts_with(&deep), "{v}");
    assert!(
        v["error"]["message"]
            .as_str()
            .unwrap()
            .contains("deeper than 48"),
        "{v}"
    );
    // Far deeper still: the same rule (the JSON nesting limit is not what answers).
    let body = json!({"session": "d", "kind": "pose_graph_2d", "factor_types": [typed(58)]});
    let (status, v) = post(&c, &s.url("/v1/sessions"), &body).await;
    assert_eq!(
        (status, &v["error"]["code"]),
        (400, &json!("invalid_factor_type")),
        "{v}"
    );
    // The maximum itself is accepted.
    let body = json!({"session": "d", "kind": "pose_graph_2d", "factor_types": [typed(45)]});
    create(&c, &s, &body).await;
}
