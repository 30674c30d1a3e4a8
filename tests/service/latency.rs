//! A latency budget (`max_update_ms`, issue 55): an update the exact solve has not reflected
//! within a quarter of the budget is answered provisionally, and the exact answer follows as a
//! correction. Streamed M3500 over HTTP and zenoh with the smallest budget (nearly every update
//! answered provisionally): every answer says whether it is exact, the corrections are
//! measured, and once idle the estimate is the batch optimum, as without a budget.

use crate::common;

use std::time::{Duration, Instant};

use common::m3500::{clean_optimum, m3500, worst_error};
use common::server::{client, create, g2o_batches, get, post, zenoh_get, TestServer};
use serde_json::{json, Value};

/// Polls the session until its estimate is within `tolerance` metres of `optimum` (the idle
/// polish ends there); returns the estimate.
async fn idle_estimate(
    c: &reqwest::Client,
    s: &TestServer,
    session: &str,
    optimum: &[factord::geometry::Se2],
) -> Value {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let (_, estimate) = get(c, &s.url(&format!("/v1/sessions/{session}/estimate"))).await;
        let worst = worst_error(&estimate, optimum);
        if worst < 1e-4 {
            return estimate;
        }
        assert!(
            Instant::now() < deadline,
            "idle, still {worst} m from the optimum"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Checks an answer to a batch sent with `wait` in a session with a budget: reflected, and
/// saying whether exactly; returns whether it was provisional.
fn provisional(ack: &Value) -> bool {
    assert_eq!(ack["solved"], true, "{ack}");
    let sequence = ack["sequence"].as_u64().unwrap();
    let exact_sequence = ack["exact_sequence"].as_u64().expect("exact_sequence");
    let exact = ack["exact"].as_bool().expect("exact");
    assert_eq!(exact, exact_sequence >= sequence, "{ack}");
    !exact
}

#[tokio::test(flavor = "multi_thread")]
async fn a_budget_answers_provisionally_and_ends_at_the_batch_optimum() {
    let Some(text) = m3500(3500) else {
        return common::skip_or_fail("input_M3500_g2o.g2o is not in the data directory")
            .unwrap_or_default();
    };
    let (_, optimum) = clean_optimum(&text);
    let s = TestServer::start(&[]);
    let c = client();
    let info = create(
        &c,
        &s,
        &json!({"session": "b", "kind": "pose_graph_2d", "max_update_ms": 1}),
    )
    .await;
    assert_eq!(info["max_update_ms"], 1);
    let url = s.url("/v1/sessions/b/batches?wait=true");
    let mut answered_provisionally = 0;
    for batch in g2o_batches(&text) {
        let (status, ack) = post(&c, &url, &batch).await;
        assert_eq!(status, 200, "{ack}");
        answered_provisionally += usize::from(provisional(&ack));
    }
    let estimate = idle_estimate(&c, &s, "b", &optimum).await;
    assert_eq!(estimate["variables"].as_array().unwrap().len(), 3500);
    let (_, stats) = get(&c, &s.url("/v1/sessions/b")).await;
    let latency = &stats["latency"];
    println!("{answered_provisionally} of 3500 answers provisional; {latency}");
    assert!(answered_provisionally > 100, "{latency}");
    assert!(latency["provisional_answers"].as_u64().unwrap() >= answered_provisionally as u64);
    assert_eq!(latency["answered_sequence"], stats["sequence"]);
    assert_eq!(latency["exact_sequence"], stats["solved_sequence"]);
    // Every provisional answer was corrected by an exact one, and the corrections are those of a
    // local solve near the robot: M3500's closures correct decimetres, not the map's scale.
    let corrections = &latency["corrections"];
    assert!(corrections["count"].as_u64().unwrap() > 0, "{latency}");
    assert!(corrections["rmse_p50"].as_f64().unwrap() < 0.5, "{latency}");
    assert!(corrections["max_p99"].as_f64().unwrap() < 20.0, "{latency}");
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn provisional_answers_reach_zenoh_subscribers_and_the_idle_estimate_is_exact() {
    let Some(text) = m3500(3500) else {
        return common::skip_or_fail("input_M3500_g2o.g2o is not in the data directory")
            .unwrap_or_default();
    };
    let (_, optimum) = clean_optimum(&text);
    let s = TestServer::start(&[]);
    let z = common::server::zenoh_peer(&s.zenoh).await;
    let rpc = |command: Value| {
        let z = z.clone();
        async move { zenoh_get(&z, "factord/rpc", Some(&command)).await.unwrap() }
    };
    rpc(
        json!({"op": "create_session", "session": "zb", "kind": "pose_graph_2d",
        "max_update_ms": 1}),
    )
    .await;
    // The estimate events carry provisional answers (their sequence is the newest batch's).
    let (_sub, events) = common::server::json_samples(&z, "factord/zb/out/poses").await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let mut answered_provisionally = 0;
    for batch in g2o_batches(&text) {
        let ack =
            rpc(json!({"op": "apply_batch", "session": "zb", "batch": batch, "wait": true})).await;
        answered_provisionally += usize::from(provisional(&ack));
    }
    assert!(answered_provisionally > 10, "{answered_provisionally}");
    let stats = rpc(json!({"op": "get_stats", "session": "zb"})).await;
    let last = stats["sequence"].as_u64().unwrap();
    // Some estimate event carried values of the newest batch before the exact solve had it.
    let mut newest_seen = 0;
    while let Ok(event) = events.recv_timeout(Duration::from_secs(5)) {
        newest_seen = newest_seen.max(event["sequence"].as_u64().unwrap());
        if newest_seen >= last {
            break;
        }
    }
    assert_eq!(
        newest_seen, last,
        "the last batch's estimate reached the subscriber"
    );
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let estimate = rpc(json!({"op": "get_estimate", "session": "zb"})).await;
        let worst = worst_error(&estimate, &optimum);
        if worst < 1e-4 {
            break;
        }
        assert!(Instant::now() < deadline, "idle, still {worst} m off");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn the_budget_survives_kill_9_and_keeps_answering() {
    let Some(text) = m3500(400) else {
        return common::skip_or_fail("input_M3500_g2o.g2o is not in the data directory")
            .unwrap_or_default();
    };
    let (_, optimum) = clean_optimum(&text);
    let dir = common::temp_dir("latency-journal");
    let s = TestServer::start_at(&dir, &[], &[]);
    let c = client();
    create(
        &c,
        &s,
        &json!({"session": "d", "kind": "pose_graph_2d", "max_update_ms": 2}),
    )
    .await;
    let batches = g2o_batches(&text);
    let url = s.url("/v1/sessions/d/batches?wait=true");
    for batch in &batches[..300] {
        let (status, ack) = post(&c, &url, batch).await;
        assert_eq!(status, 200, "{ack}");
        provisional(&ack);
    }
    s.kill();
    let s = TestServer::start_at(&dir, &[], &[]);
    common::server::recovered(&c, &s, "d", Instant::now()).await;
    let (_, info) = get(&c, &s.url("/v1/sessions/d")).await;
    assert_eq!(info["latency"]["max_update_ms"], 2, "{info}");
    let url = s.url("/v1/sessions/d/batches?wait=true");
    for batch in &batches[300..] {
        let (status, ack) = post(&c, &url, batch).await;
        assert_eq!(status, 200, "{ack}");
        provisional(&ack);
    }
    idle_estimate(&c, &s, "d", &optimum).await;
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn budgets_are_checked_and_sessions_without_one_answer_as_before() {
    let s = TestServer::start(&[]);
    let c = client();
    for (body, field) in [
        (
            json!({"kind": "pose_graph_2d", "max_update_ms": 0}),
            "max_update_ms",
        ),
        (
            json!({"kind": "pose_graph_3d", "max_update_ms": 60_001}),
            "max_update_ms",
        ),
        (
            json!({"kind": "bundle_adjustment", "max_update_ms": 20}),
            "max_update_ms",
        ),
        (
            json!({"kind": "sliding_window", "max_update_ms": 20}),
            "max_update_ms",
        ),
        (json!({"kind": "pose_graph_2d", "max_update_ms": -5}), ""),
        (
            json!({"kind": "pose_graph_2d", "max_update_ms": "fast"}),
            "",
        ),
    ] {
        let (status, e) = post(&c, &s.url("/v1/sessions"), &body).await;
        assert_eq!(status, 400, "{body}: {e}");
        if !field.is_empty() {
            assert_eq!(e["error"]["field"], field, "{body}: {e}");
        }
    }
    // Without a budget, answers carry no `exact` and statistics no `latency`.
    create(
        &c,
        &s,
        &json!({"session": "plain", "kind": "pose_graph_2d"}),
    )
    .await;
    let batch = json!({"variables": [{"key": 0, "kind": "se2", "value": [0, 0, 0], "fixed": true},
        {"key": 1, "kind": "se2", "value": [1, 0, 0]}],
        "factors": [{"type": "between_se2", "keys": [0, 1], "measurement": [1, 0, 0],
        "sigmas": [0.1, 0.1, 0.1]}]});
    let (status, ack) = post(&c, &s.url("/v1/sessions/plain/batches?wait=true"), &batch).await;
    assert_eq!(status, 200, "{ack}");
    assert!(ack.get("exact").is_none(), "{ack}");
    let (_, stats) = get(&c, &s.url("/v1/sessions/plain")).await;
    assert!(stats.get("latency").is_none(), "{stats}");
    s.assert_no_panic();
}
