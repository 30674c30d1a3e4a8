//! Group commit under `fsync always` (issue 52, item 14): many writers at once, several per
//! session, share fdatasyncs (the server's `/metrics` counts fdatasyncs and the records they
//! covered), every batch is acknowledged only once durable, and a `kill -9` in the middle of it
//! loses none that was acknowledged.

use crate::common;

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use common::server::{create, get, recovered, TestServer};
use serde_json::json;

const SESSIONS: usize = 10;
const PRODUCERS: usize = 4;

fn client() -> reqwest::Client {
    reqwest::Client::builder()
        .timeout(Duration::from_secs(10))
        .build()
        .unwrap()
}

/// The value of the counter `name` in a Prometheus text.
fn counter(text: &str, name: &str) -> f64 {
    text.lines()
        .find_map(|l| l.strip_prefix(&format!("{name} ")))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("{name} not in /metrics"))
}

#[tokio::test(flavor = "multi_thread")]
async fn concurrent_writers_share_fsyncs_and_kill_9_loses_no_acknowledged_batch() {
    let state = common::temp_dir("group-commit");
    let extra = ["--no-zenoh", "--log", "warn"];
    let s = TestServer::start_at(&state, &extra, &[]);
    let c = client();
    for i in 0..SESSIONS {
        create(
            &c,
            &s,
            &json!({"session": format!("g{i}"), "kind": "pose_graph_2d",
                    "auto_optimize": {"policy": "manual"}}),
        )
        .await;
    }
    // (session, producer) -> the last producer sequence acknowledged.
    let acked: Arc<Mutex<HashMap<(usize, usize), u64>>> = Arc::default();
    let stop = Arc::new(AtomicBool::new(false));
    let mut writers = Vec::new();
    for session in 0..SESSIONS {
        for producer in 0..PRODUCERS {
            let (c, acked, stop) = (c.clone(), Arc::clone(&acked), Arc::clone(&stop));
            let url = s.url(&format!("/v1/sessions/g{session}/batches"));
            writers.push(tokio::spawn(async move {
                for k in 1u64.. {
                    if stop.load(Ordering::SeqCst) {
                        return;
                    }
                    let key = producer as u64 * 1_000_000 + k;
                    let batch = json!({"variables": [{"key": key, "kind": "se2",
                                                      "value": [k as f64, 0, 0], "fixed": true}],
                                       "producer": format!("p{producer}"), "producer_seq": k});
                    let Ok(answer) = c.post(&url).json(&batch).send().await else {
                        return; // the server was killed
                    };
                    if answer.status() != 200 {
                        return;
                    }
                    acked.lock().unwrap().insert((session, producer), k);
                }
            }));
        }
    }
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let metrics = c
        .get(s.url("/metrics"))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    let fsyncs = counter(&metrics, "factord_journal_group_fsyncs_total");
    let records = counter(&metrics, "factord_journal_group_fsynced_records_total");
    s.kill();
    stop.store(true, Ordering::SeqCst);
    for w in writers {
        w.await.unwrap();
    }
    let acked = acked.lock().unwrap().clone();
    let total: u64 = acked.values().sum();
    eprintln!(
        "{SESSIONS} sessions x {PRODUCERS} writers: {records} records in {fsyncs} fdatasyncs \
         ({:.2} records per fdatasync) in 1.5 s; {total} batches acknowledged before the kill -9",
        records / fsyncs
    );
    assert!(total > 0, "nothing was acknowledged");
    assert!(
        records > fsyncs,
        "no fdatasync was shared: {records} records, {fsyncs} fdatasyncs"
    );

    let started = Instant::now();
    let s = TestServer::start_at(&state, &extra, &[]);
    for session in 0..SESSIONS {
        let name = format!("g{session}");
        let (stats, _) = recovered(&c, &s, &name, started).await;
        let mut through_all = 0;
        for producer in 0..PRODUCERS {
            let (status, p) = get(
                &c,
                &s.url(&format!("/v1/sessions/{name}/producers/p{producer}")),
            )
            .await;
            assert_eq!(status, 200, "{p}");
            let through = p["accepted_through"].as_u64().unwrap();
            let acknowledged = acked.get(&(session, producer)).copied().unwrap_or(0);
            assert!(
                through >= acknowledged,
                "{name} p{producer}: {through} recovered < {acknowledged} acknowledged"
            );
            through_all += through;
        }
        // Each batch once: as many batches and variables as the producers' sequences say.
        assert_eq!(stats["sequence"].as_u64().unwrap(), through_all, "{stats}");
        assert_eq!(
            stats["num_variables"].as_u64().unwrap(),
            through_all,
            "{stats}"
        );
    }
    s.assert_no_panic();
}
