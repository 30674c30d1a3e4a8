//! Oversized input is refused before it costs memory (issue 14, item 6): the server's peak RSS
//! grows by at most 4 × the bytes of the refused input, over HTTP, zenoh rpc and zenoh puts.

use crate::common;

use std::time::Duration;

use common::server::{client, create, zenoh_get, zenoh_peer, TestServer};
use serde_json::{json, Value};

/// `{"remove_factors": [1,1,…]}` of about `bytes` bytes: the cheapest way to write many items.
fn removals(bytes: usize) -> String {
    let mut text = String::with_capacity(bytes + 32);
    text.push_str("{\"remove_factors\": [1");
    while text.len() < bytes {
        text.push_str(",1");
    }
    text.push_str("]}");
    text
}

/// One factor with an information matrix of `numbers` entries, repeated to about `bytes`.
fn long_lists(bytes: usize, numbers: usize) -> String {
    let info = vec!["1"; numbers].join(",");
    let factor = format!(
        r#"{{"type": "between_se2", "keys": [0, 1], "measurement": [1, 0, 0], "information": [{info}]}}"#
    );
    let count = (bytes / factor.len()).max(1);
    format!("{{\"factors\": [{}]}}", vec![factor; count].join(","))
}

/// Resets the server's peak RSS to its current RSS (Linux `clear_refs` 5) and returns it, so
/// that each probe's peak is its own.
fn reset_peak(s: &TestServer) -> u64 {
    std::fs::write(format!("/proc/{}/clear_refs", s.pid()), "5").unwrap();
    s.peak_rss()
}

fn assert_bounded(s: &TestServer, before: u64, input_bytes: usize, what: &str) {
    let grown = s.peak_rss().saturating_sub(before);
    println!(
        "{what}: {} MB refused, peak RSS grew {} MB",
        input_bytes >> 20,
        grown >> 20
    );
    assert!(
        grown <= 4 * input_bytes as u64,
        "{what}: peak RSS grew {} MB for {} MB of refused input",
        grown >> 20,
        input_bytes >> 20
    );
}

/// Sends `rpc` over zenoh, expects a refusal, and checks the peak RSS it cost; the error body.
async fn refused_rpc(s: &TestServer, z: &zenoh::Session, rpc: &str, what: &str) -> Value {
    let payload: Value = serde_json::from_str(rpc).unwrap();
    let before = reset_peak(s);
    let e = zenoh_get(z, "factord/rpc", Some(&payload))
        .await
        .unwrap_err();
    assert_bounded(s, before, rpc.len(), what);
    e
}

#[tokio::test(flavor = "multi_thread")]
async fn oversized_bodies_are_refused_within_four_times_their_size() {
    let s = TestServer::start(&["--no-journal", "--max-body-bytes", "300000000"]);
    let c = client();
    create(&c, &s, &json!({"session": "big", "kind": "pose_graph_2d"})).await;
    let url = s.url("/v1/sessions/big/batches");
    let post = |body: String| {
        let c = c.clone();
        let url = url.clone();
        async move {
            let r = c
                .post(&url)
                .header("content-type", "application/json")
                .body(body)
                .send()
                .await
                .unwrap();
            let status = r.status().as_u16();
            (status, r.json::<Value>().await.unwrap())
        }
    };

    // Three 80 MB bodies of 40 M removals each, at once.
    let before = reset_peak(&s);
    let bodies: Vec<_> = (0..3).map(|_| removals(80 << 20)).collect();
    let total: usize = bodies.iter().map(String::len).sum();
    let answers = futures_util::future::join_all(bodies.into_iter().map(post)).await;
    for (status, v) in answers {
        assert_eq!(status, 413, "{v}");
        assert_eq!(v["error"]["code"], "batch_too_large", "{v}");
    }
    assert_bounded(&s, before, total, "HTTP removals");

    // Lists inside items longer than any kind takes: refused before decoding.
    let before = reset_peak(&s);
    let body = long_lists(60 << 20, 1 << 20);
    let len = body.len();
    let (status, v) = post(body).await;
    assert_eq!(status, 413, "{v}");
    assert_eq!(v["error"]["code"], "list_too_long", "{v}");
    assert_bounded(&s, before, len, "HTTP long lists");

    // zenoh: an rpc batch, an rpc with a huge key list, and a put.
    let z = zenoh_peer(&s.zenoh).await;
    zenoh_get(&z, "factord/rpc", Some(&json!({"op": "health"})))
        .await
        .unwrap();
    let batch = removals(50 << 20);
    let rpc = format!(r#"{{"op": "apply_batch", "session": "big", "batch": {batch}}}"#);
    let e = refused_rpc(&s, &z, &rpc, "zenoh rpc batch").await;
    assert_eq!(e["error"]["code"], "batch_too_large", "{e}");

    let keys = vec!["7"; 25 << 20].join(",");
    let rpc = format!(r#"{{"op": "get_marginals", "session": "big", "keys": [{keys}]}}"#);
    let e = refused_rpc(&s, &z, &rpc, "zenoh rpc keys").await;
    assert_eq!(e["error"]["status"], 413, "{e}");

    let errors = z
        .declare_subscriber("factord/big/out/errors")
        .await
        .unwrap();
    let before = reset_peak(&s);
    let put = removals(60 << 20);
    z.put("factord/big/in/batch", put.clone())
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .unwrap();
    let sample = tokio::time::timeout(Duration::from_secs(30), errors.recv_async())
        .await
        .expect("a refusal on out/errors")
        .unwrap();
    let event: Value = serde_json::from_slice(&sample.payload().to_bytes()).unwrap();
    assert_eq!(event["error"]["code"], "batch_too_large", "{event}");
    assert_bounded(&s, before, put.len(), "zenoh put");
    z.close().await.unwrap();
    s.assert_no_panic();
}

/// zenoh payloads obey `max_body_bytes` as HTTP bodies do.
#[tokio::test(flavor = "multi_thread")]
async fn zenoh_payloads_beyond_max_body_bytes_are_refused() {
    let s = TestServer::start(&["--no-journal", "--max-body-bytes", "1000000"]);
    let z = zenoh_peer(&s.zenoh).await;
    let create = json!({"op": "create_session", "session": "z", "kind": "pose_graph_2d"});
    zenoh_get(&z, "factord/rpc", Some(&create)).await.unwrap();
    let batch: Value = serde_json::from_str(&removals(2_000_000)).unwrap();
    let rpc = json!({"op": "apply_batch", "session": "z", "batch": batch});
    let e = zenoh_get(&z, "factord/rpc", Some(&rpc)).await.unwrap_err();
    assert_eq!(e["error"]["code"], "body_too_large", "{e}");
    assert_eq!(e["error"]["field"], "payload", "{e}");
    z.close().await.unwrap();
}
