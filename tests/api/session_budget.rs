//! A session's work stays within its bounds when one factor is expensive (issue 52, item 7):
//! a user-defined type near the cost bound makes one iteration take seconds, yet a DELETE stops
//! the running solve at once, a solve stops near `max_solve_ms`, and a batch whose admission
//! would outlast `max_admission_ms` is refused. Each against a real `factord serve`.

use crate::common;

use std::time::{Duration, Instant};

use common::server::{client, create, delete_session, get, post, start_with_limits, TestServer};
use serde_json::{json, Value};

/// Chains of compositions in the heavy type, and compositions per chain: about 1 800 distinct
/// SE(2) compositions, within the 4096 nodes and depth 48 of a definition and under its cost
/// bound. Measured on a loaded 2-core machine: admitting one factor ~0.5 ms, one linearisation
/// of 6 000 of them ~5 s.
const CHAINS: usize = 44;
const DEPTH: usize = 40;

/// A residual over poses `a`, `b` and a measured pose `z` that no solver can shorten: the norm
/// of the translations of `CHAINS` long products, each starting from a different constant.
fn heavy_type() -> Value {
    let terms: Vec<Value> = (0..CHAINS)
        .map(|c| {
            let mut e =
                json!({"compose": ["a", {"se2": [0.01 * c as f64, 0.0, 0.001 * c as f64]}]});
            for d in 0..DEPTH {
                e = json!({"compose": [e, if d % 2 == 0 { "b" } else { "z" }]});
            }
            json!({"translation": [e]})
        })
        .collect();
    json!({
        "name": "heavy",
        "variables": [{"name": "a", "kind": "se2"}, {"name": "b", "kind": "se2"}],
        "parameters": [{"name": "z", "kind": "se2"}],
        "residual": {"norm": [terms]}
    })
}

/// A session with the heavy type, solved only when asked, with options no tolerance stops.
async fn heavy_session(c: &reqwest::Client, s: &TestServer, name: &str) {
    let options = json!({"max_iterations": 1000, "function_tolerance": 0.0,
        "gradient_tolerance": 0.0, "parameter_tolerance": 0.0,
        "method": "gauss_newton", "initialization": "none"});
    create(
        c,
        s,
        &json!({"session": name, "kind": "pose_graph_2d", "options": options,
            "auto_optimize": {"policy": "manual"}, "factor_types": [heavy_type()]}),
    )
    .await;
}

/// A batch of `factors` heavy factors over `poses` poses starting at key `first` (new poses
/// from `first`, each factor between two of them).
fn heavy_batch(first: u64, poses: u64, factors: u64, with_poses: bool) -> Value {
    let variables: Vec<Value> = if with_poses {
        (first..first + poses)
            .map(|k| json!({"key": k, "kind": "se2", "value": [0.1 * k as f64, 0.2, 0.01 * k as f64]}))
            .collect()
    } else {
        Vec::new()
    };
    let factors: Vec<Value> = (0..factors)
        .map(|f| {
            let (i, j) = (first + f % poses, first + (f * 7 + 1) % poses);
            let j = if i == j {
                first + (j - first + 1) % poses
            } else {
                j
            };
            json!({"type": "heavy", "keys": [i, j], "measurement": [0.5, 0.1, 0.02],
                   "information": [1.0]})
        })
        .collect();
    json!({"variables": variables, "factors": factors})
}

/// Adds `factors` heavy factors over 200 poses, in batches small enough to be admitted well
/// within any `max_admission_ms` used here (150 factors: ~0.1 s).
async fn fill(c: &reqwest::Client, s: &TestServer, name: &str, factors: u64) {
    let url = s.url(&format!("/v1/sessions/{name}/batches"));
    let (status, v) = post(c, &url, &heavy_batch(0, 200, 0, true)).await;
    assert_eq!(status, 200, "{v}");
    const PER_BATCH: u64 = 150;
    let mut added = 0;
    while added < factors {
        let (status, v) = post(
            c,
            &url,
            &heavy_batch(0, 200, PER_BATCH.min(factors - added), false),
        )
        .await;
        assert_eq!(status, 200, "{v}");
        added += PER_BATCH;
    }
}

/// The server process's CPU time (user + system), from /proc (clock ticks of 1/100 s, the value
/// on every Linux we run on).
fn cpu_seconds(pid: u32) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).expect("/proc/<pid>/stat");
    // The command name may hold spaces: the fields counted from after its closing parenthesis.
    let after = &stat[stat.rfind(')').expect("a stat line") + 2..];
    let fields: Vec<&str> = after.split_whitespace().collect();
    // utime and stime are fields 14 and 15 of the line, 12 and 13 after the name.
    let ticks: u64 = fields[11].parse::<u64>().unwrap() + fields[12].parse::<u64>().unwrap();
    ticks as f64 / 100.0
}

async fn wait_solving(c: &reqwest::Client, s: &TestServer, name: &str) {
    let deadline = Instant::now() + Duration::from_secs(20);
    while get(c, &s.url(&format!("/v1/sessions/{name}"))).await.1["solving"] != true {
        assert!(Instant::now() < deadline, "the solve did not start");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// Before: the solve ran to the end of its first evaluation and iteration (seconds of a full
/// core) after the DELETE was answered. Now it stops at its next budget checkpoint.
#[tokio::test(flavor = "multi_thread")]
async fn a_deleted_sessions_solve_stops_at_once() {
    let s = start_with_limits(&json!({"max_solve_ms": 120_000}));
    let c = client();
    heavy_session(&c, &s, "doomed").await;
    fill(&c, &s, "doomed", 6000).await;
    let url = s.url("/v1/sessions/doomed/optimize");
    assert_eq!(post(&c, &url, &json!({})).await.0, 202);
    wait_solving(&c, &s, "doomed").await;
    // Deep inside the first linearisation (seconds long before the fix).
    tokio::time::sleep(Duration::from_millis(300)).await;
    let (status, v) = delete_session(&c, &s, "doomed").await;
    assert_eq!(status, 200, "{v}");
    // A checkpoint comes within ~0.1 s of work (longer on a loaded machine); then the process
    // should be idle. Two seconds, so that a solve still running shows even when it gets only
    // a fraction of a core.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let before = cpu_seconds(s.pid());
    tokio::time::sleep(Duration::from_secs(2)).await;
    let used = cpu_seconds(s.pid()) - before;
    eprintln!("CPU in the 2 s after DELETE (+0.5 s): {used:.2} s");
    assert!(
        used < 0.1,
        "the deleted session's solve still ran: {used:.2} s of CPU in 2 s"
    );
    s.assert_no_panic();
}

/// Before: a solve whose one iteration takes seconds overran a one-second limit by that
/// iteration (6.4 s measured). Now it stops within a chunk of factors of the limit.
#[tokio::test(flavor = "multi_thread")]
async fn a_solve_with_a_slow_iteration_stops_near_max_solve_ms() {
    let limit = Duration::from_millis(300);
    let s = start_with_limits(&json!({"max_solve_ms": limit.as_millis() as u64}));
    let c = client();
    heavy_session(&c, &s, "slow").await;
    fill(&c, &s, "slow", 12_000).await;
    let start = Instant::now();
    let url = s.url("/v1/sessions/slow/optimize?wait=true");
    let (status, v) = post(&c, &url, &json!(null)).await;
    let wall = start.elapsed();
    eprintln!("solve with max_solve_ms {limit:?}: answered in {wall:?}: {v}");
    assert_eq!(status, 200, "{v}");
    // The first evaluation of the cost finishes even out of time (~0.4 s here when idle).
    assert!(wall < Duration::from_secs(2), "{wall:?}");
    let (_, info) = get(&c, &s.url("/v1/sessions/slow")).await;
    let error = info["last_error"].as_str().unwrap_or_default();
    assert!(error.contains("max_solve_ms"), "{info}");
    s.assert_no_panic();
}

/// Before: a batch of heavy factors was admitted however long building and checking them took
/// (24 s in the issue; 12.8 s here). Now it is refused whole once it outlasts
/// `max_admission_ms`, and the same factors in smaller batches are admitted.
#[tokio::test(flavor = "multi_thread")]
async fn a_batch_whose_admission_outlasts_max_admission_ms_is_refused() {
    let limit = Duration::from_millis(1000);
    let s = start_with_limits(&json!({"max_admission_ms": limit.as_millis() as u64}));
    let c = client();
    heavy_session(&c, &s, "big").await;
    let url = s.url("/v1/sessions/big/batches");
    let batch = heavy_batch(0, 200, 20_000, true);
    let start = Instant::now();
    let (status, v) = post(&c, &url, &batch).await;
    let wall = start.elapsed();
    eprintln!("20 000 heavy factors in one batch: {status} in {wall:?}: {v}");
    assert_eq!(status, 413, "{v}");
    assert_eq!(v["error"]["code"], "batch_too_costly", "{v}");
    assert_eq!(v["error"]["field"], "factors", "{v}");
    assert!(
        v["error"]["message"]
            .as_str()
            .unwrap()
            .contains("max_admission_ms"),
        "{v}"
    );
    assert!(wall < 3 * limit, "{wall:?}");
    let (_, info) = get(&c, &s.url("/v1/sessions/big")).await;
    assert_eq!(
        info["num_factors"], 0,
        "nothing of the refused batch applied: {info}"
    );
    fill(&c, &s, "big", 500).await;
    s.assert_no_panic();
}
