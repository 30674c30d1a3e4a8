//! A bundle adjustment session on more than one thread: the threads beyond its own worker are
//! borrowed from idle workers of the server's pool (`--workers`), never more. The sessions give
//! `threads` alone: the other options stay the kind's (Levenberg-Marquardt damped from the
//! first step), where they once fell back to the pose graphs' Gauss-Newton, which a free gauge
//! makes singular.

use crate::common;

use common::server::{client, create, get, post, TestServer};
use serde_json::{json, Value};

/// Solves problem-49 in a session asking for `threads` (and no other option) on a server of
/// `workers`; returns the summary.
async fn solve_with(text: &str, workers: &str, threads: u64) -> Value {
    let s = TestServer::start(&["--no-zenoh", "--workers", workers]);
    let c = client();
    create(
        &c,
        &s,
        &json!({"session": "ba", "kind": "bundle_adjustment", "auto_optimize": {"policy": "manual"},
                "options": {"threads": threads}}),
    )
    .await;
    let (status, info) = get(&c, &s.url("/v1/sessions/ba")).await;
    assert_eq!(status, 200, "{info}");
    let mut kinds = serde_json::to_value(factord::solver::SolverOptions::bundle_adjustment())
        .expect("options serialise");
    kinds["threads"] = json!(threads);
    assert_eq!(info["options"], kinds, "threads given, the rest the kind's");
    let (variables, factors) = common::bal_session::batches(text, 10_000);
    let url = s.url("/v1/sessions/ba/batches");
    for b in std::iter::once(&variables).chain(&factors) {
        let (status, v) = post(&c, &url, b).await;
        assert_eq!(status, 200, "{v}");
    }
    let (status, done) = post(&c, &s.url("/v1/sessions/ba/optimize?wait=true"), &json!({})).await;
    assert_eq!(status, 200, "{done}");
    let (status, summary) = get(&c, &s.url("/v1/sessions/ba/summary")).await;
    assert_eq!(status, 200, "{summary}");
    s.assert_no_panic();
    summary
}

#[tokio::test(flavor = "multi_thread")]
async fn a_session_solves_on_the_idle_workers_it_borrows_and_no_more() {
    let Some(path) = common::data_file("bal/problem-49-7776-pre.txt") else {
        return;
    };
    let text = std::fs::read_to_string(&path).unwrap();
    let mut costs = Vec::new();
    // (workers, threads asked, threads the solve may run on): 0 asks for the whole pool.
    for (workers, asked, expected) in [("2", 2, 2), ("1", 2, 1), ("3", 0, 3), ("2", 1, 1)] {
        let summary = solve_with(&text, workers, asked).await;
        assert_eq!(
            summary["used"]["threads"], expected,
            "workers {workers}, threads {asked}: {summary}"
        );
        let cost = summary["final_chi2"].as_f64().unwrap() / 2.0;
        assert!((cost - 13344.32).abs() < 1e-3 * 13344.32, "{cost}");
        costs.push(cost);
    }
    // Threads change only the order of sums: the same optimum to rounding.
    for cost in &costs {
        assert!((cost - costs[0]).abs() <= 1e-9 * costs[0], "{costs:?}");
    }
}

/// A pose graph's solve does not split: asking for threads borrows no worker, and another
/// session's batch is answered while the first solves.
#[tokio::test(flavor = "multi_thread")]
async fn a_pose_graph_session_asking_for_threads_borrows_nothing() {
    let s = TestServer::start(&["--no-zenoh", "--workers", "2"]);
    let c = client();
    create(
        &c,
        &s,
        &json!({"session": "pg", "kind": "pose_graph_2d", "auto_optimize": {"policy": "manual"},
                "options": {"threads": 2}}),
    )
    .await;
    let variables: Vec<Value> = (0..50)
        .map(|i| json!({"key": i, "kind": "se2", "value": [i as f64, 0.0, 0.0]}))
        .collect();
    let factors: Vec<Value> = (1..50)
        .map(|i| json!({"type": "between_se2", "keys": [i - 1, i], "measurement": [1.0, 0.0, 0.01], "sigmas": [0.1, 0.1, 0.05]}))
        .chain([json!({"type": "prior_se2", "keys": [0], "measurement": [0.0, 0.0, 0.0], "sigmas": [0.01, 0.01, 0.01]})])
        .collect();
    let (status, v) = post(
        &c,
        &s.url("/v1/sessions/pg/batches"),
        &json!({"variables": variables, "factors": factors}),
    )
    .await;
    assert_eq!(status, 200, "{v}");
    let (status, done) = post(&c, &s.url("/v1/sessions/pg/optimize?wait=true"), &json!({})).await;
    assert_eq!(status, 200, "{done}");
    let (_, summary) = get(&c, &s.url("/v1/sessions/pg/summary")).await;
    // The solve is given the threads it may run on: this one, and none borrowed.
    assert_eq!(summary["used"]["threads"], 1, "{summary}");
    assert_eq!(summary["given_options"]["threads"], 1, "{summary}");
    s.assert_no_panic();
}
