//! Configured caps over real sockets: each one answers a clear 4xx (or stops the solve and
//! says so) instead of growing without bound.

use crate::common;

use common::server::{client, g2o_batches, get, post, TestServer};
use serde_json::{json, Value};

fn server_with_limits(limits: Value) -> TestServer {
    let dir = common::temp_dir("limits");
    let config = dir.join("config.json");
    std::fs::write(&config, json!({ "limits": limits }).to_string()).unwrap();
    TestServer::start(&["--no-zenoh", "--config", config.to_str().unwrap()])
}

fn variables(keys: std::ops::Range<u64>) -> Value {
    let v: Vec<Value> = keys
        .map(|k| json!({"key": k, "kind": "se2", "value": [k as f64, 0, 0]}))
        .collect();
    json!({ "variables": v })
}

#[tokio::test(flavor = "multi_thread")]
async fn batch_session_and_subscriber_caps_answer_4xx() {
    let s = server_with_limits(json!({
        "max_batch_items": 10, "max_variables_per_session": 20,
        "max_factors_per_session": 3, "max_subscribers": 2}));
    let c = client();
    let (status, _) = post(&c, &s.url("/v1/sessions"), &json!({"session": "capped", "kind": "pose_graph_2d", "auto_optimize": {"policy": "manual"}})).await;
    assert_eq!(status, 201);
    let url = s.url("/v1/sessions/capped/batches");

    let (status, v) = post(&c, &url, &variables(0..11)).await;
    assert_eq!(status, 413, "{v}");
    assert_eq!(
        (v["error"]["code"].as_str(), v["error"]["field"].as_str()),
        (Some("batch_too_large"), Some("batch"))
    );
    assert_eq!(post(&c, &url, &variables(0..10)).await.0, 200);
    assert_eq!(post(&c, &url, &variables(10..20)).await.0, 200);
    let (status, v) = post(&c, &url, &variables(20..21)).await;
    assert_eq!(status, 422, "{v}");
    assert_eq!(
        (v["error"]["code"].as_str(), v["error"]["field"].as_str()),
        (Some("session_full"), Some("variables"))
    );

    let between = |a: u64| json!({"type": "between_se2", "keys": [a, a + 1], "measurement": [1, 0, 0], "sigmas": [1, 1, 1]});
    let factors = json!({"factors": [between(0), between(1), between(2)]});
    assert_eq!(post(&c, &url, &factors).await.0, 200);
    let (status, v) = post(&c, &url, &json!({"factors": [between(3)]})).await;
    assert_eq!(
        (status, v["error"]["field"].as_str()),
        (422, Some("factors")),
        "{v}"
    );
    // Removing one makes room for one.
    let (status, v) = post(
        &c,
        &url,
        &json!({"factors": [between(3)], "remove_factors": [0]}),
    )
    .await;
    assert_eq!(status, 200, "{v}");
    let (_, stats) = get(&c, &s.url("/v1/sessions/capped")).await;
    assert_eq!(
        (
            stats["num_variables"].as_u64(),
            stats["num_factors"].as_u64()
        ),
        (Some(20), Some(3))
    );
    assert!(stats["memory_bytes"].as_u64().unwrap() > 20 * 24);

    // Two subscribers are allowed, the third is told to come back later.
    let events = s.url("/v1/sessions/capped/events");
    let first = c.get(&events).send().await.unwrap();
    let second = c.get(&events).send().await.unwrap();
    assert_eq!(
        (first.status().as_u16(), second.status().as_u16()),
        (200, 200)
    );
    let third = c.get(&events).send().await.unwrap();
    assert_eq!(third.status(), 429);
    assert!(third.headers().contains_key("retry-after"));
    let v: Value = third.json().await.unwrap();
    assert_eq!(v["error"]["code"], "too_many_subscribers");
    drop(first);
    let mut admitted = false;
    for _ in 0..100 {
        let again = c.get(&events).send().await.unwrap();
        if again.status() == 200 {
            admitted = true;
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    assert!(admitted, "a subscriber that left frees its place");
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn a_solve_stops_at_the_time_limit_and_says_so() {
    let s = server_with_limits(json!({"max_solve_ms": 1}));
    let c = client();
    let (status, _) = post(&c, &s.url("/v1/sessions"), &json!({"session": "slow", "kind": "pose_graph_2d",
        "auto_optimize": {"policy": "manual"}, "options": {"method": "levenberg_marquardt", "initialization": "none"}})).await;
    assert_eq!(status, 201);
    let (mut vars, mut factors) = (Vec::new(), Vec::new());
    for b in g2o_batches(&common::synthetic_manhattan(3000, 8)) {
        vars.extend(b["variables"].as_array().unwrap().iter().cloned());
        factors.extend(b["factors"].as_array().unwrap().iter().cloned());
    }
    let batch = json!({"variables": vars, "factors": factors});
    assert_eq!(
        post(&c, &s.url("/v1/sessions/slow/batches"), &batch)
            .await
            .0,
        200
    );
    let (status, v) = post(
        &c,
        &s.url("/v1/sessions/slow/optimize?wait=true"),
        &json!(null),
    )
    .await;
    assert_eq!(status, 200, "{v}");
    let error = v["stats"]["last_error"].as_str().unwrap_or_default();
    assert!(error.contains("time limit of 1 ms"), "{v}");
    assert_eq!(v["stats"]["converged"], false);
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn a_batch_job_stops_at_the_time_limit_with_its_best_estimate() {
    let s = server_with_limits(json!({"max_solve_ms": 1}));
    let c = client();
    let text = common::synthetic_manhattan(3000, 8);
    let response = c
        .post(s.url("/v1/jobs?method=lm&init=none"))
        .body(text)
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), 200);
    let v: Value = response.json().await.unwrap();
    assert_eq!(
        v["summary"]["termination"]["reason"], "interrupted",
        "{}",
        v["summary"]
    );
    assert_eq!(v["estimate"]["variables"].as_array().unwrap().len(), 3000);
    s.assert_no_panic();
}

/// B37: a session past `limits.max_session_memory_bytes` takes no more variables or factors,
/// names the limit, keeps what it had, and still lets a client remove factors; other
/// sessions go on.
#[tokio::test(flavor = "multi_thread")]
async fn a_session_past_its_memory_limit_takes_nothing_more_but_removals() {
    let limit: u64 = 256 << 10;
    let s = server_with_limits(json!({ "max_session_memory_bytes": limit }));
    let c = client();
    for name in ["big", "small"] {
        let create = json!({"session": name, "kind": "pose_graph_2d", "auto_optimize": {"policy": "manual"}});
        assert_eq!(post(&c, &s.url("/v1/sessions"), &create).await.0, 201);
    }
    let url = s.url("/v1/sessions/big/batches");
    let between = |a: u64| json!({"type": "between_se2", "keys": [a, a + 1], "measurement": [1, 0, 0], "sigmas": [1, 1, 1]});
    let mut next = 0u64;
    let refused = loop {
        let factors: Vec<Value> = (next..next + 50).map(between).collect();
        let mut batch = variables(next..next + 51);
        batch["factors"] = json!(factors);
        if next > 0 {
            // Key `next` is already there.
            batch["variables"] = json!(batch["variables"].as_array().unwrap()[1..]);
        }
        let (status, v) = post(&c, &url, &batch).await;
        if status != 200 {
            break (status, v);
        }
        next += 50;
        assert!(next < 100_000, "the limit never refused a batch");
    };
    let (status, v) = refused;
    assert_eq!(status, 422, "{v}");
    assert_eq!(
        (v["error"]["code"].as_str(), v["error"]["field"].as_str()),
        (Some("session_full"), Some("batch"))
    );
    let message = v["error"]["message"].as_str().unwrap();
    assert!(
        message.contains("limits.max_session_memory_bytes"),
        "{message}"
    );
    let (_, stats) = get(&c, &s.url("/v1/sessions/big")).await;
    assert!(stats["memory_bytes"].as_u64().unwrap() > limit, "{stats}");
    assert_eq!(stats["num_variables"].as_u64(), Some(next + 1));
    // Removing is how a client makes room: it passes.
    let (status, v) = post(&c, &url, &json!({"remove_factors": [0, 1]})).await;
    assert_eq!(status, 200, "{v}");
    // Another session is not affected.
    let small = s.url("/v1/sessions/small/batches");
    assert_eq!(post(&c, &small, &variables(0..10)).await.0, 200);
}
