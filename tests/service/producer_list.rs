//! `GET /v1/sessions/{session}/producers` and the rpc `list_producers`: every producer that sent
//! the session a numbered batch, sorted by id, with where its batches stand; the command added
//! end to end as the proof of "one command, one file" (issue 53).

use crate::common;

use common::server::{client, create, g2o_batches, get, post, zenoh_get, zenoh_peer, TestServer};
use serde_json::{json, Value};

fn numbered(mut batch: Value, producer: &str, seq: u64) -> Value {
    batch["producer"] = json!(producer);
    batch["producer_seq"] = json!(seq);
    batch
}

#[tokio::test(flavor = "multi_thread")]
async fn the_producers_of_a_session_are_listed_with_their_progress() {
    let s = TestServer::start(&[]);
    let c = client();
    create(&c, &s, &json!({"session": "pl", "kind": "pose_graph_2d"})).await;
    let url = s.url("/v1/sessions/pl/producers");
    let (status, empty) = get(&c, &url).await;
    assert_eq!(status, 200, "{empty}");
    assert_eq!(empty, json!({"session": "pl", "producers": []}));

    let batches = g2o_batches(&common::synthetic_manhattan(30, 3));
    let batch_url = s.url("/v1/sessions/pl/batches");
    let mut last = Value::Null;
    for (i, (producer, seq)) in [("r2", 1), ("r1", 1), ("r2", 2)].into_iter().enumerate() {
        let (status, ack) =
            post(&c, &batch_url, &numbered(batches[i].clone(), producer, seq)).await;
        assert!(status < 300, "{ack}");
        last = ack;
    }
    // An unnumbered batch has no producer to list.
    let (status, ack) = post(&c, &batch_url, &batches[3]).await;
    assert!(status < 300, "{ack}");

    let (status, list) = get(&c, &url).await;
    assert_eq!(status, 200, "{list}");
    let producers = list["producers"].as_array().expect("a list");
    let ids: Vec<&str> = producers
        .iter()
        .map(|p| p["producer"].as_str().unwrap())
        .collect();
    assert_eq!(ids, ["r1", "r2"], "{list}");
    assert_eq!(producers[1]["accepted_through"], 2);
    assert_eq!(producers[1]["sequence"], last["sequence"]);
    assert_eq!(producers[0]["accepted_through"], 1);
    // Each entry is what `GET …/producers/{producer}` answers for it.
    let (_, one) = get(&c, &s.url("/v1/sessions/pl/producers/r1")).await;
    for field in ["session", "producer", "accepted_through", "sequence"] {
        assert_eq!(producers[0][field], one[field], "{field}: {list} vs {one}");
    }

    // The same command over zenoh's rpc, which needed no change for it.
    let z = zenoh_peer(&s.zenoh).await;
    let rpc = json!({"op": "list_producers", "session": "pl"});
    let over_zenoh = zenoh_get(&z, "factord/rpc", Some(&rpc)).await.unwrap();
    assert_eq!(
        over_zenoh["producers"].as_array().map(Vec::len),
        Some(2),
        "{over_zenoh}"
    );
    assert_eq!(over_zenoh["producers"][1]["accepted_through"], 2);

    let (status, missing) = get(&c, &s.url("/v1/sessions/nope/producers")).await;
    assert_eq!(status, 404, "{missing}");
    s.assert_no_panic();
}
