//! Sliding-window latency through zenoh against the real `factord serve`: a robot publishes
//! each keyframe's messages (its IMU samples, the keyframe, its relative pose and prior) on
//! `factord/<s>/in/fusion` once the previous keyframe's state has arrived, and times the arrival
//! of the state on `out/state`. Also reports the server's own update time (keyframe arrival to
//! optimised state, marginalisation included) from the state events.
//!
//! `cargo bench --bench fusion_latency -- [--window 20] [--seconds 140] [--json out.json]`
//! Needs `../shared/data/imu/euroc_V1_01_easy` (or FACTORD_DATA).

#[path = "../../tests/common/mod.rs"]
mod common;

use std::time::{Duration, Instant};

use common::fusion::{inputs, keyframe_batches, position_error, start_message};
use common::server::{zenoh_get, zenoh_peer, TestServer};
use serde_json::{json, Value};

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() as f64 - 1.0) * p).round() as usize]
}

fn stats(mut v: Vec<f64>) -> Value {
    v.sort_by(f64::total_cmp);
    json!({"p50": percentile(&v, 0.5), "p90": percentile(&v, 0.9), "p99": percentile(&v, 0.99),
           "max": v[v.len() - 1], "count": v.len()})
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    let value = |flag: &str| {
        args.iter()
            .position(|a| a == flag)
            .and_then(|i| args.get(i + 1).cloned())
    };
    let window: usize = value("--window").map_or(20, |v| v.parse().expect("--window N"));
    let seconds: f64 = value("--seconds").map_or(140.0, |v| v.parse().expect("--seconds S"));
    let Some(inputs) = inputs(seconds, window) else {
        eprintln!("no EuRoC data: nothing measured");
        return;
    };
    let server = TestServer::start(&[]);
    let z = zenoh_peer(&server.zenoh).await;
    zenoh_get(
        &z,
        "factord/rpc",
        Some(&json!({"op": "create_session", "session": "bench", "kind": "sliding_window"})),
    )
    .await
    .expect("session created");
    let (tx, states) = std::sync::mpsc::channel::<(Instant, Value)>();
    let tx = std::sync::Mutex::new(tx);
    let _subscriber = z
        .declare_subscriber("factord/bench/out/state")
        .callback(move |sample| {
            let v = serde_json::from_slice(&sample.payload().to_bytes()).unwrap();
            let _ = tx.lock().unwrap().send((Instant::now(), v));
        })
        .await
        .unwrap();
    zenoh_get(&z, "factord/rpc", Some(&json!({"op": "health"})))
        .await
        .unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    let put = |messages: Vec<Value>| {
        let z = z.clone();
        async move {
            let body = serde_json::to_vec(&json!({ "messages": messages })).unwrap();
            z.put("factord/bench/in/fusion", body).await.unwrap();
        }
    };
    put(vec![start_message(&inputs)]).await;
    let (mut latency, mut update, mut errors) = (Vec::new(), Vec::new(), Vec::new());
    for batch in keyframe_batches(&inputs) {
        let sent = Instant::now();
        put(batch).await;
        let (arrived, state) = states
            .recv_timeout(Duration::from_secs(5))
            .expect("a state per keyframe");
        latency.push(arrived.duration_since(sent).as_secs_f64() * 1e3);
        update.push(state["update_seconds"].as_f64().unwrap() * 1e3);
        errors.push(position_error(&inputs, &state["state"]));
    }
    let rmse = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt();
    let result = json!({
        "window": window,
        "keyframes": errors.len(),
        "publish_to_state_ms": stats(latency),
        "server_update_ms": stats(update),
        "ape_trans_rmse": rmse,
    });
    println!("{}", serde_json::to_string_pretty(&result).unwrap());
    if let Some(path) = value("--json") {
        std::fs::write(path, result.to_string()).unwrap();
    }
    server.assert_no_panic();
}
