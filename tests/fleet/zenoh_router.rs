//! A robot that reaches the server through a zenoh router receives the session's events.
//!
//! The server puts an event only on topics some subscriber matches (zenoh's matching status):
//! a subscriber behind a router must count, or a robot connected that way would never hear its
//! poses. Here the server is a peer connected to a router, the robot a zenoh client of the
//! same router, as on a robot whose zenoh talks to a router on the vehicle or in the site.

use crate::common;

use std::sync::mpsc;
use std::time::{Duration, Instant};

use common::server::{client, create, free_port, post, zenoh_session, TestServer};
use serde_json::{json, Value};

/// The batch that adds pose `key` after pose `key - 1`, one metre ahead.
fn step(key: u64) -> Value {
    json!({
        "variables": [{"key": key, "kind": "se2"}],
        "factors": [{"type": "between_se2", "keys": [key - 1, key],
                     "measurement": [1.0, 0.0, 0.0], "information": [1, 0, 0, 1, 0, 1]}],
    })
}

#[tokio::test(flavor = "multi_thread")]
async fn a_robot_behind_a_router_receives_poses_and_acks() {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let _router = zenoh_session("router", "listen", &endpoint).await;
    let s = TestServer::start(&["--zenoh-connect", &endpoint]);
    let c = client();
    let url = |path: &str| s.url(&format!("/v1/sessions{path}"));
    create(&c, &s, &json!({"session": "r", "kind": "pose_graph_2d"})).await;
    let first =
        json!({"variables": [{"key": 0, "kind": "se2", "value": [0, 0, 0], "fixed": true}]});
    let (status, v) = post(&c, &url("/r/batches"), &first).await;
    assert_eq!(status, 200, "{v}");

    // One subscriber on the poses' own key, one on every topic of the session.
    let z = zenoh_session("client", "connect", &endpoint).await;
    let (tx, events) = mpsc::channel::<(String, Value)>();
    let mut subscribers = Vec::new();
    for key in ["factord/r/out/poses", "factord/r/out/**"] {
        let tx = std::sync::Mutex::new(tx.clone());
        let key = key.to_string();
        subscribers.push(
            z.declare_subscriber(key.clone())
                .callback(move |sample| {
                    let v = serde_json::from_slice(&sample.payload().to_bytes()).unwrap();
                    let _ = tx.lock().unwrap().send((key.clone(), v));
                })
                .await
                .unwrap(),
        );
    }

    // Until the server learns of the subscriptions (through the router) its events reach
    // nobody: append poses until one is heard.
    let mut key = 0;
    let deadline = Instant::now() + Duration::from_secs(20);
    let mut heard = false;
    while !heard && Instant::now() < deadline {
        key += 1;
        let (status, v) = post(&c, &url("/r/batches?wait=true"), &step(key)).await;
        assert_eq!(status, 200, "{v}");
        tokio::time::sleep(Duration::from_millis(100)).await;
        heard = events.try_iter().count() > 0;
    }
    assert!(
        heard,
        "no event reached the robot through the router in 20 s"
    );

    // From then on, every batch's new pose reaches both subscribers, and its ack the wildcard.
    let from = key + 1;
    let to = key + 20;
    let mut last_sequence = 0;
    for key in from..=to {
        let (status, v) = post(&c, &url("/r/batches?wait=true"), &step(key)).await;
        assert_eq!(status, 200, "{v}");
        last_sequence = v["sequence"].as_u64().unwrap();
    }
    // Per subscription (the poses' key, the wildcard) the poses heard, and the acks heard.
    let mut poses_of = [Vec::new(), Vec::new()];
    let mut acked = Vec::new();
    let complete = |poses_of: &[Vec<u64>; 2], acked: &[u64]| {
        poses_of.iter().all(|p| p.contains(&to)) && acked.contains(&last_sequence)
    };
    let deadline = Instant::now() + Duration::from_secs(10);
    while !complete(&poses_of, &acked) && Instant::now() < deadline {
        let Ok((subscription, v)) = events.recv_timeout(Duration::from_millis(200)) else {
            continue;
        };
        let wildcard = subscription.ends_with("**") as usize;
        match v["type"].as_str() {
            Some("estimate") => {
                for variable in v["variables"].as_array().unwrap() {
                    poses_of[wildcard].push(variable["key"].as_u64().unwrap());
                }
            }
            Some("ack") => acked.push(v["sequence"].as_u64().unwrap()),
            _ => {}
        }
    }
    for (poses, subscription) in poses_of.iter().zip(["out/poses", "out/**"]) {
        let missing: Vec<u64> = (from..=to).filter(|k| !poses.contains(k)).collect();
        assert!(
            missing.is_empty(),
            "poses {missing:?} never reached the robot's {subscription}"
        );
    }
    assert!(
        acked.contains(&last_sequence),
        "the last batch's ack never reached the robot: {acked:?}"
    );
    drop(subscribers);
    z.close().await.unwrap();
    s.assert_no_panic();
}
