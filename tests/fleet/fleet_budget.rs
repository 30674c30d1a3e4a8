//! A session with a latency budget (`max_update_ms`, issue 55) in a fleet: when its owner is
//! killed with -9, the survivor that adopts it from the journal keeps the budget, answers the
//! stream's next updates within it (provisionally where the exact solve lags), and ends at the
//! batch optimum once idle, every acknowledged batch there once.

use crate::common;

use std::time::{Duration, Instant};

use common::fleet::Fleet;
use common::server::{g2o_batches, zenoh_peer};
use serde_json::{json, Value};

const BUDGET_MS: u64 = 20;
const POSES: usize = 600;
const KILL_AFTER: usize = 250;

/// Posts until the session answers (a 503 or a refused connection while it moves is retried,
/// for at most 20 s); the status and JSON answer.
async fn post_served(c: &reqwest::Client, url: &str, body: &Value) -> (u16, Value) {
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let answer = c
            .post(url)
            .header("content-type", "application/json")
            .body(body.to_string())
            .send()
            .await;
        match answer {
            Ok(a) if a.status().as_u16() != 503 => {
                let status = a.status().as_u16();
                return (status, a.json().await.unwrap_or(Value::Null));
            }
            _ if Instant::now() >= deadline => panic!("{url}: not served within 20 s"),
            _ => tokio::time::sleep(Duration::from_millis(20)).await,
        }
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn an_adopted_session_keeps_its_latency_budget() {
    let mut fleet = Fleet::start(2, &[]);
    let z = zenoh_peer(&fleet.instance(0).zenoh).await;
    fleet.wait_settled(&z).await;
    let c = reqwest::Client::builder()
        .timeout(Duration::from_secs(30))
        .build()
        .unwrap();
    // A session that instance 1 owns, reached through instance 0 (which survives).
    let name = (0..64)
        .map(|i| format!("budget-{i}"))
        .find(|n| fleet.owner(n) == 1)
        .expect("placement gives instance 1 some name");
    let survivor = fleet.instance(0).http.clone();
    let (status, v) = post_served(
        &c,
        &format!("{survivor}/v1/sessions"),
        &json!({"session": name, "kind": "pose_graph_2d", "max_update_ms": BUDGET_MS}),
    )
    .await;
    assert_eq!(status, 201, "{v}");
    let graph = common::synthetic_manhattan(POSES, 5);
    let url = format!("{survivor}/v1/sessions/{name}/batches?wait=true");
    let mut provisional = 0;
    for (k, mut batch) in g2o_batches(&graph).into_iter().enumerate() {
        if k == KILL_AFTER {
            fleet.kill(1);
        }
        batch["producer"] = json!("robot");
        batch["producer_seq"] = json!(k + 1);
        let (status, ack) = post_served(&c, &url, &batch).await;
        assert_eq!(status, 200, "batch {}: {ack}", k + 1);
        // A resend of a batch whose ack the kill lost is answered as a duplicate (applied
        // once); the session's sequence below counts what was applied.
        match ack["exact"].as_bool() {
            Some(true) => {}
            Some(false) => provisional += 1,
            None => panic!("a budget session's ack says whether it is exact: {ack}"),
        }
    }
    assert_eq!(fleet.owner(&name), 0, "the survivor adopted it");
    let info_url = format!("{survivor}/v1/sessions/{name}");
    let deadline = Instant::now() + Duration::from_secs(60);
    let info = loop {
        let info: Value = c.get(&info_url).send().await.unwrap().json().await.unwrap();
        if info["converged"] == true && info["pending_batches"] == 0 {
            break info;
        }
        assert!(Instant::now() < deadline, "never idle: {info}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    assert_eq!(info["latency"]["max_update_ms"], BUDGET_MS, "{info}");
    assert_eq!(info["num_variables"], POSES, "{info}");
    assert_eq!(info["sequence"], POSES, "every batch applied once: {info}");
    eprintln!(
        "{provisional} provisional answers; latency stats after adoption: {}",
        info["latency"]
    );
    // Idle, the adopted session is at the batch optimum of what it holds.
    let (optimum, _) = common::m3500::clean_optimum(&graph);
    let chi2 = info["chi2"].as_f64().unwrap();
    assert!(
        (chi2 - optimum).abs() <= 1e-5 * optimum,
        "idle chi2 {chi2} vs batch optimum {optimum}"
    );
}
