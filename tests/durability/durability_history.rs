//! A durable session's history (the web view's timeline, event log and rejected inputs) outlives
//! its server, against the real binary: written to the session's directory once a second and at
//! shutdown, it comes back after a `kill -9` and after a graceful stop, and new solves extend
//! it; a damaged history file costs the history, never the session.

use crate::common;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use common::server::{client, create, get, post, recovered, TestServer};
use serde_json::{json, Value};

const SESSION: &str = "robot";

fn history_file(state: &Path) -> PathBuf {
    state.join("sessions").join(SESSION).join("history.json")
}

/// Pose `key` one metre after the previous one, joined to it by odometry that disagrees a
/// little with the guess (pose 0 alone): every batch needs a solve (one that adds no chi2 is
/// reflected without one, and makes no timeline point).
fn pose_batch(key: u64) -> Value {
    let variable = json!({"key": key, "kind": "se2", "value": [key as f64, 0.1, 0.0]});
    if key == 0 {
        return json!({"variables": [variable]});
    }
    json!({
        "variables": [variable],
        "factors": [{"type": "between_se2", "keys": [key - 1, key], "measurement": [1, 0.05, 0.02],
                     "information": [100, 0, 0, 100, 0, 400]}],
    })
}

async fn send_pose(c: &reqwest::Client, s: &TestServer, key: u64) {
    let url = s.url(&format!("/v1/sessions/{SESSION}/batches?wait=true"));
    let (status, v) = post(c, &url, &pose_batch(key)).await;
    assert_eq!(status, 200, "{v}");
}

async fn history(c: &reqwest::Client, s: &TestServer) -> Value {
    let (status, v) = get(c, &s.url(&format!("/v1/sessions/{SESSION}/history"))).await;
    assert_eq!(status, 200, "{v}");
    v
}

/// The history once the session is idle (its summaries, and the idle polish's, are in): two
/// reads 1.5 s apart with the same timeline, at least `points` long.
async fn settled(c: &reqwest::Client, s: &TestServer, points: usize) -> Value {
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut last = history(c, s).await;
    loop {
        tokio::time::sleep(Duration::from_millis(1500)).await;
        let now = history(c, s).await;
        if now["timeline"] == last["timeline"] && items(&now, "timeline").len() >= points {
            return now;
        }
        assert!(
            Instant::now() < deadline,
            "the history never settled: {now}"
        );
        last = now;
    }
}

fn items<'a>(history: &'a Value, field: &str) -> &'a Vec<Value> {
    history[field].as_array().expect("an array")
}

/// Waits until the history file holds `timeline` points and `rejected` rejections.
fn written(state: &Path, timeline: usize, rejected: usize) -> Value {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let stored = std::fs::read(history_file(state))
            .ok()
            .and_then(|bytes| serde_json::from_slice::<Value>(&bytes).ok());
        if let Some(stored) = stored {
            let count = |field: &str| stored[field].as_array().map(Vec::len);
            if (count("timeline"), count("rejected")) == (Some(timeline), Some(rejected)) {
                return stored;
            }
        }
        assert!(
            Instant::now() < deadline,
            "history file never held {timeline} points and {rejected} rejections: {:?}",
            std::fs::read_to_string(history_file(state))
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// A server on `state` with the session created and fed `poses` poses, one solve each.
async fn streamed(c: &reqwest::Client, state: &Path, poses: u64) -> TestServer {
    let s = TestServer::start_at(state, &["--no-zenoh"], &[]);
    create(c, &s, &json!({"session": SESSION, "kind": "pose_graph_2d"})).await;
    for key in 0..poses {
        send_pose(c, &s, key).await;
    }
    s
}

/// Starts a server on `state` and waits for the session to be rebuilt.
async fn restart(c: &reqwest::Client, state: &Path) -> TestServer {
    let s = TestServer::start_at(state, &["--no-zenoh"], &[]);
    recovered(c, &s, SESSION, Instant::now()).await;
    s
}

#[tokio::test(flavor = "multi_thread")]
async fn the_history_comes_back_after_kill_9_and_after_a_graceful_stop() {
    let state = common::temp_dir("history");
    let c = client();
    let s = streamed(&c, &state, 6).await;
    // A factor on a pose that does not exist: refused, and kept among the rejected inputs.
    let bad = json!({"factors": [{"type": "between_se2", "keys": [5, 99], "measurement": [1, 0, 0],
                                  "information": [100, 0, 0, 100, 0, 400]}]});
    let (status, v) = post(&c, &s.url(&format!("/v1/sessions/{SESSION}/batches")), &bad).await;
    assert_eq!(status, 422, "{v}");
    // One timeline point per solve (each update's summary follows its ack).
    let before = settled(&c, &s, 6).await;
    let points = items(&before, "timeline").len();
    assert_eq!(items(&before, "rejected").len(), 1, "{before}");
    written(&state, points, 1);
    s.kill();

    // After kill -9: the timeline, the log and the rejection as they were, then what the
    // recovery's solve adds.
    let s = restart(&c, &state).await;
    let after = history(&c, &s).await;
    for field in ["timeline", "events", "rejected"] {
        let (old, new) = (items(&before, field), items(&after, field));
        assert!(new.len() >= old.len(), "{field}: {after}");
        assert_eq!(&new[..old.len()], &old[..], "{field} came back as it was");
    }
    assert_eq!(
        after["rejected"][0]["data"]["error"]["field"],
        "factors[0].keys[1]"
    );
    assert_eq!(after["dropped"], before["dropped"]);
    // New solves extend it.
    send_pose(&c, &s, 6).await;
    let extended = settled(&c, &s, items(&after, "timeline").len() + 1).await;
    let newest = items(&extended, "timeline").last().unwrap();
    assert_eq!(newest["sequence"], 7, "{newest}");

    // A graceful stop right after a solve (before the once-a-second pass) writes it too.
    send_pose(&c, &s, 7).await;
    let (status, log) = s.terminate(Duration::from_secs(20));
    assert!(status.is_some_and(|s| s.success()), "{log}");
    let s = restart(&c, &state).await;
    let again = history(&c, &s).await;
    assert!(
        items(&again, "timeline").iter().any(|p| p["sequence"] == 8),
        "the last solve before the stop is in the timeline: {again}"
    );
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn a_damaged_history_file_costs_the_history_not_the_session() {
    let state = common::temp_dir("history-damaged");
    let c = client();
    let s = streamed(&c, &state, 4).await;
    let points = items(&settled(&c, &s, 4).await, "timeline").len();
    written(&state, points, 0);
    s.kill();
    for damage in [
        &b"{\"format\": 1, \"timeline\": [{\"unix_ms\": "[..],
        b"{\"format\": 99}",
    ] {
        std::fs::write(history_file(&state), damage).unwrap();
        let s = restart(&c, &state).await;
        let (status, stats) = get(&c, &s.url(&format!("/v1/sessions/{SESSION}"))).await;
        assert_eq!((status, &stats["sequence"]), (200, &json!(4)), "{stats}");
        // Only what this process did: the recovery's solve.
        let fresh = settled(&c, &s, 0).await;
        assert!(items(&fresh, "timeline").len() <= 1, "{fresh}");
        // Replaced by a whole file at the next pass.
        let stored = written(&state, items(&fresh, "timeline").len(), 0);
        assert_eq!(stored["format"], 1);
        let log = s.kill();
        assert!(
            log.contains("history file unreadable") || log.contains("history file has format 99"),
            "the damage is logged:\n{log}"
        );
        assert!(!log.contains("panicked"), "{log}");
    }
}
