//! Exactly-once ingest against the real binary: batches carry `producer` and `producer_seq`; a
//! repeat is answered with its original acknowledgement and applied no second time, a gap is
//! refused naming the number expected, and both hold across `kill -9` and a restart (journal
//! and snapshots). Requests that say "after my batches" wait for them across transports.

use crate::common;

use std::time::{Duration, Instant};

use common::server::{client, create, g2o_batches, get, post, recovered, zenoh_peer, TestServer};
use serde_json::{json, Value};

fn with_producer(mut batch: Value, producer: &str, seq: u64) -> Value {
    batch["producer"] = json!(producer);
    batch["producer_seq"] = json!(seq);
    batch
}

async fn stats(c: &reqwest::Client, s: &TestServer, name: &str) -> Value {
    let (status, v) = get(c, &s.url(&format!("/v1/sessions/{name}"))).await;
    assert_eq!(status, 200, "{v}");
    v
}

#[tokio::test(flavor = "multi_thread")]
async fn repeats_get_their_original_ack_and_gaps_are_refused() {
    let s = TestServer::start(&[]);
    let c = client();
    create(&c, &s, &json!({"session": "eo", "kind": "pose_graph_2d"})).await;
    let batches = g2o_batches(&common::synthetic_manhattan(40, 3));
    let url = s.url("/v1/sessions/eo/batches");

    let (status, first) = post(&c, &url, &with_producer(batches[0].clone(), "r1", 1)).await;
    assert!(status < 300, "{first}");
    assert_eq!(first["accepted_through"], 1);
    assert_eq!(first["producer_seq"], 1);
    assert!(first.get("duplicate").is_none(), "{first}");
    let (_, second) = post(&c, &url, &with_producer(batches[1].clone(), "r1", 2)).await;
    assert_eq!(second["accepted_through"], 2, "{second}");

    // A repeat: the original acknowledgement, nothing applied.
    let before = stats(&c, &s, "eo").await;
    let (status, again) = post(&c, &url, &with_producer(batches[1].clone(), "r1", 2)).await;
    assert!(status < 300, "{again}");
    assert_eq!(again["duplicate"], true, "{again}");
    for field in ["sequence", "factor_ids", "predicted", "producer_seq"] {
        assert_eq!(again[field], second[field], "{field}: {again} vs {second}");
    }
    let after = stats(&c, &s, "eo").await;
    assert!(before["num_factors"].as_u64().unwrap() > 0, "{before}");
    assert_eq!(after["num_factors"], before["num_factors"]);
    assert_eq!(after["num_variables"], before["num_variables"]);

    // A gap: refused, naming what is expected; nothing applied.
    let (status, gap) = post(&c, &url, &with_producer(batches[3].clone(), "r1", 4)).await;
    assert_eq!(status, 409, "{gap}");
    assert_eq!(gap["error"]["code"], "producer_sequence_gap");
    assert_eq!(gap["error"]["field"], "producer_seq");
    assert!(
        gap["error"]["message"]
            .as_str()
            .unwrap()
            .contains("expects batch 3"),
        "{gap}"
    );

    // A refused batch does not use its number: fixed, it is sent again with the same one.
    let mut broken = with_producer(batches[2].clone(), "r1", 3);
    broken["factors"][0]["keys"] = json!([2, 999]);
    let (status, refused) = post(&c, &url, &broken).await;
    assert!((400..500).contains(&status), "{refused}");
    let (status, third) = post(&c, &url, &with_producer(batches[2].clone(), "r1", 3)).await;
    assert!(status < 300, "{third}");
    assert_eq!(third["accepted_through"], 3);

    // Another producer counts on its own.
    let (status, other) = post(&c, &url, &with_producer(batches[3].clone(), "r2", 1)).await;
    assert!(status < 300, "{other}");
    assert_eq!(other["accepted_through"], 1);

    let (status, progress) = get(&c, &s.url("/v1/sessions/eo/producers/r1")).await;
    assert_eq!(status, 200, "{progress}");
    assert_eq!(progress["accepted_through"], 3);
    assert_eq!(progress["sequence"], third["sequence"]);
    let (_, unknown) = get(&c, &s.url("/v1/sessions/eo/producers/nobody")).await;
    assert_eq!(unknown["accepted_through"], 0);
    let (status, bad) = get(&c, &s.url("/v1/sessions/eo/producers/no%20body")).await;
    assert_eq!(status, 400, "{bad}");
    assert_eq!(bad["error"]["code"], "invalid_producer");
    let (status, bad) = get(
        &c,
        &s.url("/v1/sessions/eo/estimate?after_producer=a%2Fb&after_seq=1"),
    )
    .await;
    assert_eq!(status, 400, "{bad}");
    assert_eq!(bad["error"]["field"], "after_producer");

    // Half the fields, a bad id: 400 naming the field.
    for (body, field) in [
        (json!({"producer": "r1"}), "producer_seq"),
        (json!({"producer_seq": 5}), "producer"),
        (json!({"producer": "r/1", "producer_seq": 1}), "producer"),
        (json!({"producer": "r1", "producer_seq": 0}), "producer_seq"),
    ] {
        let (status, e) = post(&c, &url, &body).await;
        assert_eq!(status, 400, "{body}: {e}");
        assert_eq!(e["error"]["field"], field, "{body}: {e}");
    }
    s.assert_no_panic();
}

/// kill -9 at points where the producer's progress lives only in the journal, only in a
/// snapshot, and in both: every repeat is recognised after the restart.
#[tokio::test(flavor = "multi_thread")]
async fn repeats_are_recognised_after_kill_9_from_journal_and_snapshot() {
    let state = common::temp_dir("exactly-once-state");
    let config = state.parent().unwrap().join("eo-config.json");
    std::fs::write(
        &config,
        json!({"journal": {"snapshot_every": 7}}).to_string(),
    )
    .unwrap();
    let config = config.display().to_string();
    let batches = g2o_batches(&common::synthetic_manhattan(60, 5));
    let c = client();
    let mut acks: Vec<Value> = Vec::new();
    let mut sent = 0;
    for round in 0..3 {
        let s = TestServer::start_at(&state, &["--config", &config], &[]);
        if round == 0 {
            create(&c, &s, &json!({"session": "eo", "kind": "pose_graph_2d"})).await;
        } else {
            recovered(&c, &s, "eo", Instant::now()).await;
        }
        let url = s.url("/v1/sessions/eo/batches");
        // Everything sent so far, again: all duplicates with their original acks.
        for (k, ack) in acks.iter().enumerate() {
            let seq = k as u64 + 1;
            let (status, again) =
                post(&c, &url, &with_producer(batches[k].clone(), "robot", seq)).await;
            assert!(status < 300, "round {round}, seq {seq}: {again}");
            assert_eq!(
                again["duplicate"], true,
                "round {round}, seq {seq}: {again}"
            );
            assert_eq!(again["factor_ids"], ack["factor_ids"], "seq {seq}");
            assert_eq!(again["sequence"], ack["sequence"], "seq {seq}");
        }
        for _ in 0..17 {
            let seq = sent as u64 + 1;
            let (status, ack) = post(
                &c,
                &url,
                &with_producer(batches[sent].clone(), "robot", seq),
            )
            .await;
            assert!(status < 300, "{ack}");
            assert!(ack.get("duplicate").is_none(), "{ack}");
            acks.push(ack);
            sent += 1;
        }
        let st = stats(&c, &s, "eo").await;
        let expected: usize = batches[..sent]
            .iter()
            .map(|b| b["factors"].as_array().unwrap().len())
            .sum();
        assert_eq!(st["num_factors"], expected, "round {round}: {st}");
        s.kill();
    }
}

/// An estimate read over HTTP that says `after` the producer's last zenoh put sees it, though
/// the put and the read travel separately; waiting for a batch that never comes times out with
/// 503 `after_timeout`.
#[tokio::test(flavor = "multi_thread")]
async fn reads_after_a_producers_batches_see_them_across_transports() {
    let s = TestServer::start(&[]);
    let c = client();
    create(&c, &s, &json!({"session": "ord", "kind": "pose_graph_2d"})).await;
    let z = zenoh_peer(&s.zenoh).await;
    let batches = g2o_batches(&common::synthetic_manhattan(300, 9));
    let publisher = z
        .declare_publisher("factord/ord/in/batch")
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .unwrap();
    // Let the subscription reach the publisher before the first put.
    tokio::time::sleep(Duration::from_millis(300)).await;
    for (k, b) in batches.iter().enumerate() {
        let seq = k as u64 + 1;
        publisher
            .put(with_producer(b.clone(), "z1", seq).to_string())
            .await
            .unwrap();
        if seq % 50 == 0 || seq as usize == batches.len() {
            let url = s.url(&format!(
                "/v1/sessions/ord/estimate?after_producer=z1&after_seq={seq}"
            ));
            let (status, estimate) = get(&c, &url).await;
            assert_eq!(status, 200, "{estimate}");
            let keys = estimate["variables"].as_array().unwrap().len();
            assert!(keys >= seq as usize, "after {seq}: {keys} variables");
        }
    }
    let (status, optimized) = post(
        &c,
        &s.url(&format!(
            "/v1/sessions/ord/optimize?wait=true&after_producer=z1&after_seq={}",
            batches.len()
        )),
        &json!({}),
    )
    .await;
    assert_eq!(status, 200, "{optimized}");
    assert_eq!(optimized["stats"]["num_variables"], batches.len());

    let started = Instant::now();
    let (status, late) = get(
        &c,
        &s.url("/v1/sessions/ord/estimate?after_producer=z1&after_seq=100000&after_timeout_ms=300"),
    )
    .await;
    assert_eq!(status, 503, "{late}");
    assert_eq!(late["error"]["code"], "after_timeout");
    assert_eq!(late["error"]["field"], "after_seq");
    assert!(started.elapsed() >= Duration::from_millis(300));
    let (status, bad) = get(&c, &s.url("/v1/sessions/ord/estimate?after_seq=3")).await;
    assert_eq!(status, 400, "{bad}");
    assert_eq!(bad["error"]["field"], "after_producer");
    z.close().await.unwrap();
    s.assert_no_panic();
}

/// One pose per batch or a hundred (beyond the size the server decodes where it receives, so
/// those are decoded ahead on another thread while the batch before them is applied), mixed on
/// one zenoh publisher: acknowledged in the order sent; a large refused batch in between is
/// reported with its producer and changes nothing; a large put for no session is refused on
/// that session's `out/errors`.
#[tokio::test(flavor = "multi_thread")]
async fn puts_decoded_ahead_are_applied_in_the_order_sent() {
    let s = TestServer::start(&[]);
    let c = client();
    create(
        &c,
        &s,
        &json!({"session": "ahead", "kind": "pose_graph_2d"}),
    )
    .await;
    let z = zenoh_peer(&s.zenoh).await;
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel::<(String, Value)>();
    let _events = z
        .declare_subscriber("factord/*/out/*")
        .callback(move |sample| {
            if let Ok(v) = serde_json::from_slice::<Value>(&sample.payload().to_bytes()) {
                let _ = tx.send((sample.key_expr().as_str().to_string(), v));
            }
        })
        .await
        .unwrap();
    let publisher = z
        .declare_publisher("factord/ahead/in/batch")
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;

    // Chunks of 1 and 100 poses, alternating.
    let poses = g2o_batches(&common::synthetic_manhattan(1010, 4));
    let mut chunks: Vec<Value> = Vec::new();
    let mut rest = &poses[..];
    while !rest.is_empty() {
        let take = if chunks.len() % 2 == 0 { 1 } else { 100 }.min(rest.len());
        let (chunk, tail) = rest.split_at(take);
        let mut merged = json!({"variables": [], "factors": []});
        for b in chunk {
            for part in ["variables", "factors"] {
                let items = b[part].as_array().unwrap().clone();
                merged[part].as_array_mut().unwrap().extend(items);
            }
        }
        chunks.push(merged);
        rest = tail;
    }
    assert!(
        chunks[1].to_string().len() > 20_000,
        "a large chunk is large"
    );
    // A large batch refused on its last factor (a measurement of the wrong length).
    let mut bad = chunks[1].clone();
    let last = bad["factors"].as_array().unwrap().len() - 1;
    bad["factors"][last]["measurement"] = json!([1.0, 2.0]);
    bad["variables"] = json!([]);
    let bad = with_producer(bad, "bad", 1);
    // A batch that is not a batch (a field this server does not know): refused at decoding,
    // still reported with its numbering, so its producer learns of it instead of waiting.
    let mut undecodable = with_producer(json!({"variables": [], "factors": []}), "typo", 1);
    undecodable["factorz"] = json!([]);

    for (k, chunk) in chunks.iter().enumerate() {
        let body = with_producer(chunk.clone(), "p", k as u64 + 1).to_string();
        publisher.put(body).await.unwrap();
        if k == chunks.len() / 2 {
            publisher.put(bad.to_string()).await.unwrap();
            publisher.put(undecodable.to_string()).await.unwrap();
        }
    }
    z.put("factord/nobody/in/batch", bad.to_string())
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .unwrap();

    let mut acked = Vec::new();
    let (mut refused, mut nobody, mut typo) = (None, None, None);
    let deadline = Instant::now() + Duration::from_secs(30);
    while acked.len() < chunks.len() || refused.is_none() || nobody.is_none() || typo.is_none() {
        let left = deadline.saturating_duration_since(Instant::now());
        let Ok(Some((key, v))) = tokio::time::timeout(left, rx.recv()).await else {
            panic!(
                "acked {} of {}, refused {refused:?}, nobody {nobody:?}, typo {typo:?}",
                acked.len(),
                chunks.len()
            );
        };
        match key.as_str() {
            "factord/ahead/out/acks" if v["producer"] == "p" => {
                acked.push(v["producer_seq"].as_u64().unwrap())
            }
            "factord/ahead/out/errors" if v["producer"] == "typo" => typo = Some(v),
            "factord/ahead/out/errors" => refused = Some(v),
            "factord/nobody/out/errors" => nobody = Some(v),
            _ => {}
        }
    }
    let expected: Vec<u64> = (1..=chunks.len() as u64).collect();
    assert_eq!(acked, expected, "acks in the order the batches were sent");
    let refused = refused.unwrap();
    assert_eq!(refused["producer"], "bad", "{refused}");
    assert_eq!(refused["error"]["code"], "wrong_dimension", "{refused}");
    assert_eq!(
        refused["error"]["field"],
        format!("factors[{last}].measurement"),
        "{refused}"
    );
    let nobody = nobody.unwrap();
    assert_eq!(nobody["error"]["code"], "unknown_session", "{nobody}");
    let typo = typo.unwrap();
    assert_eq!(typo["producer_seq"], 1, "{typo}");
    assert!(
        typo["error"]["message"].to_string().contains("factorz"),
        "{typo}"
    );

    let st = stats(&c, &s, "ahead").await;
    let factors: usize = chunks
        .iter()
        .map(|b| b["factors"].as_array().unwrap().len())
        .sum();
    assert_eq!(st["num_variables"], poses.len(), "{st}");
    assert_eq!(st["num_factors"], factors, "{st}");
    z.close().await.unwrap();
    s.assert_no_panic();
}
