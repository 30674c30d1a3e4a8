//! A landing larger than one slice (issue 55): a loop closure into a 9 000-pose map moves more
//! variables than the session writes into its mirror per hold of its lock (4 096), so the solve's
//! values go out slice by slice, each in an `estimate` event of its own, while batches keep
//! arriving with a latency budget. A zenoh subscriber that applies the events in order ends with
//! the session's estimate, once idle, to the last digit.

use crate::common;

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use common::server::{
    client, create, g2o_batches, get, json_samples, post, zenoh_peer, TestServer,
};
use serde_json::{json, Value};

/// The session's slice (`provisional/landing.rs`).
const SLICE: usize = 4096;

/// Consecutive single-pose batches merged into one of `poses` poses.
fn merged(batches: &[Value], poses: usize) -> Vec<Value> {
    batches
        .chunks(poses)
        .map(|chunk| {
            let mut variables = Vec::new();
            let mut factors = Vec::new();
            for batch in chunk {
                variables.extend(batch["variables"].as_array().unwrap().iter().cloned());
                factors.extend(batch["factors"].as_array().unwrap().iter().cloned());
            }
            json!({"variables": variables, "factors": factors})
        })
        .collect()
}

/// Applies an estimate event's variables to `view` (key → value); returns how many it carried.
fn apply(view: &mut BTreeMap<u64, Value>, event: &Value) -> usize {
    let variables = event["variables"].as_array().expect("an estimate event");
    for v in variables {
        view.insert(v["key"].as_u64().unwrap(), v["value"].clone());
    }
    variables.len()
}

#[tokio::test(flavor = "multi_thread")]
async fn a_landing_larger_than_a_slice_reaches_subscribers_in_order() {
    let text = common::synthetic_manhattan(9000, 7);
    let s = TestServer::start(&[]);
    let c = client();
    create(
        &c,
        &s,
        &json!({"session": "big", "kind": "pose_graph_2d", "max_update_ms": 20}),
    )
    .await;
    let z = zenoh_peer(&s.zenoh).await;
    let (_sub, events) = json_samples(&z, "factord/big/out/poses").await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let url = s.url("/v1/sessions/big/batches?wait=true");
    for batch in merged(&g2o_batches(&text), 60) {
        let (status, ack) = post(&c, &url, &batch).await;
        assert_eq!(status, 200, "{ack}");
    }
    // Idle: every batch solved exactly and the estimate no longer changing.
    let deadline = Instant::now() + Duration::from_secs(120);
    let mut last: Option<Value> = None;
    let estimate = loop {
        let (_, stats) = get(&c, &s.url("/v1/sessions/big")).await;
        let (_, estimate) = get(&c, &s.url("/v1/sessions/big/estimate")).await;
        if stats["solved_sequence"] == stats["sequence"] && last.as_ref() == Some(&estimate) {
            break estimate;
        }
        assert!(Instant::now() < deadline, "not idle: {stats}");
        last = Some(estimate);
        tokio::time::sleep(Duration::from_millis(500)).await;
    };
    let variables = estimate["variables"].as_array().unwrap();
    assert_eq!(variables.len(), 9000);
    // What the subscriber heard, in order: the values, and per sequence the sizes of the events.
    // A subscriber that falls behind gets one event with every value changed since (any size).
    let mut view = BTreeMap::new();
    let mut per_sequence: BTreeMap<u64, Vec<usize>> = BTreeMap::new();
    while let Ok(event) = events.recv_timeout(Duration::from_secs(2)) {
        let carried = apply(&mut view, &event);
        per_sequence
            .entry(event["sequence"].as_u64().unwrap())
            .or_default()
            .push(carried);
    }
    // A sliced landing: a correction of the whole map changes every value of a slice, so its
    // first slices carry exactly a slice each (a landing in one event carries all it moved).
    let slices = per_sequence
        .values()
        .flatten()
        .filter(|&&n| n == SLICE)
        .count();
    println!("{slices} events of a whole slice; per sequence: {per_sequence:?}");
    assert!(slices > 0, "no landing was heard in slices");
    for v in variables {
        let key = v["key"].as_u64().unwrap();
        assert_eq!(
            view.get(&key),
            Some(&v["value"]),
            "variable {key}: the subscriber's value is not the session's"
        );
    }
    s.assert_no_panic();
}
