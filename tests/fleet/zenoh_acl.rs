//! zenoh's access control as configured by docker/zenoh-secure.json5 (its LAN interface set to
//! loopback here): the rpc and writes into `ops-` sessions are refused, streaming into other
//! sessions works.

use crate::common;

use std::time::Duration;

use common::server::{client, create, get, zenoh_peer, TestServer};
use serde_json::json;

/// Replies to a query on `key` within a second (a refused query gets none).
async fn replies(z: &zenoh::Session, key: &str, payload: &serde_json::Value) -> usize {
    let receiver = z
        .get(key)
        .payload(payload.to_string())
        .timeout(Duration::from_secs(1))
        .await
        .unwrap();
    let mut n = 0;
    while receiver.recv_async().await.is_ok() {
        n += 1;
    }
    n
}

#[tokio::test(flavor = "multi_thread")]
async fn the_example_acl_refuses_rpc_and_ops_sessions_from_the_lan() {
    let example = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/docker/zenoh-secure.json5"
    ))
    .unwrap();
    assert!(example.contains("interfaces: [\"eth0\"]"));
    let dir = common::temp_dir("zenoh-acl");
    let config = dir.join("zenoh.json5");
    std::fs::write(
        &config,
        example.replace("interfaces: [\"eth0\"]", "interfaces: [\"lo\"]"),
    )
    .unwrap();
    let s = TestServer::start(&["--zenoh-config", config.to_str().unwrap()]);
    let c = client();
    for name in ["robot-1", "ops-map"] {
        create(&c, &s, &json!({"session": name, "kind": "pose_graph_2d"})).await;
    }
    let z = zenoh_peer(&s.zenoh).await;
    tokio::time::sleep(Duration::from_millis(500)).await;

    // The rpc is refused: the query reaches nothing.
    let health = json!({"op": "health"});
    assert_eq!(
        replies(&z, "factord/rpc", &health).await,
        0,
        "rpc answered through the ACL"
    );
    // Reads of a session's estimate are not rpc: allowed.
    assert_eq!(
        replies(&z, "factord/robot-1/estimate", &json!(null)).await,
        1
    );

    let batch = json!({"variables": [{"key": 0, "kind": "se2", "value": [0, 0, 0]}]}).to_string();
    for name in ["robot-1", "ops-map"] {
        z.put(format!("factord/{name}/in/batch"), batch.clone())
            .await
            .unwrap();
    }
    let mut sequences = (0, 0);
    for _ in 0..50 {
        tokio::time::sleep(Duration::from_millis(50)).await;
        let (_, robot) = get(&c, &s.url("/v1/sessions/robot-1")).await;
        let (_, ops) = get(&c, &s.url("/v1/sessions/ops-map")).await;
        sequences = (
            robot["sequence"].as_u64().unwrap(),
            ops["sequence"].as_u64().unwrap(),
        );
        if sequences.0 == 1 {
            break;
        }
    }
    // Give a wrongly admitted put the same time to land, then check it did not.
    tokio::time::sleep(Duration::from_millis(300)).await;
    let (_, ops) = get(&c, &s.url("/v1/sessions/ops-map")).await;
    assert_eq!(sequences.0, 1, "the put into robot-1 was refused");
    assert_eq!(
        ops["sequence"], 0,
        "the put into ops-map got through the ACL"
    );
    z.close().await.unwrap();
    s.assert_no_panic();
}
