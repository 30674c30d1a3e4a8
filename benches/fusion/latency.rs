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

#[path = "../args.rs"]
mod args;

use common::eval::experiment::{ape, Percentiles};
use common::eval::fusion_client::run_over_zenoh;
use common::fusion::inputs;
use common::server::TestServer;
use serde_json::json;

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let args = args::Args::from_env();
    let window: usize = args.parsed("--window", 20);
    let seconds: f64 = args.parsed("--seconds", 140.0);
    let Some(inputs) = inputs(seconds, window) else {
        eprintln!("no EuRoC data: nothing measured");
        return;
    };
    let server = TestServer::start(&[]);
    let estimates = run_over_zenoh(&server.zenoh, "bench", &inputs)
        .await
        .expect("the stream runs");
    let ms = |f: &dyn Fn(&common::eval::experiment::Estimate) -> f64| {
        Percentiles::of(&estimates.iter().map(|e| f(e) * 1e3).collect::<Vec<_>>())
    };
    let result = json!({
        "window": window,
        "keyframes": estimates.len(),
        "publish_to_state_ms": ms(&|e| e.latency_seconds.expect("streamed")),
        "server_update_ms": ms(&|e| e.update_seconds),
        "ape_trans_rmse": ape(&inputs, &estimates).1.rmse,
    });
    println!("{}", serde_json::to_string_pretty(&result).unwrap());
    if let Some(path) = args.value("--json") {
        std::fs::write(path, result.to_string()).unwrap();
    }
    server.assert_no_panic();
}
