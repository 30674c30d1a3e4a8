//! Scenario `ingest`: 1000-factor batches (chunks of a generated Manhattan graph, every pose
//! with its guess) published at full rate over zenoh into `factord serve --fsync interval`,
//! session policy `manual` (ingest alone, no solve competing; `--policy default` keeps the
//! server's default). Same run, same payloads: a bare zenoh echo peer (its own process, which
//! answers each put with a small ack put and parses nothing) as the reference of what zenoh
//! itself carries on this machine.

use std::time::Duration;

use serde_json::{json, Value};
use zenoh::Wait;

use crate::graph;
use crate::proc::{zenoh_peer, EchoPeer};
use crate::stream::{publish_all, run_one, stream_report};

/// The echo peer's body (`__echo <listen>`): every put on `echo/in/batch` is answered on
/// `echo/out/acks` with an ack whose numbers are the count of puts received (zenoh delivers
/// one publisher's puts in order).
pub fn echo_main(listen: &str) {
    let mut c = zenoh::Config::default();
    c.insert_json5("mode", "\"peer\"").expect("mode");
    c.insert_json5("scouting/multicast/enabled", "false")
        .expect("scouting");
    c.insert_json5("listen/endpoints", &format!("[\"{listen}\"]"))
        .expect("listen");
    let z = zenoh::open(c).wait().expect("zenoh opens");
    let publisher = z
        .declare_publisher("echo/out/acks")
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .wait()
        .expect("publisher");
    let received = std::sync::atomic::AtomicU64::new(0);
    let _sub = z
        .declare_subscriber("echo/in/batch")
        .callback(move |_sample| {
            let n = received.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            let ack = format!(
                "{{\"type\":\"ack\",\"producer\":\"robot\",\"producer_seq\":{n},\"accepted_through\":{n}}}"
            );
            let _ = publisher.put(ack).wait();
        })
        .wait()
        .expect("subscriber");
    loop {
        std::thread::sleep(Duration::from_secs(3600));
    }
}

/// `ingest [--batches 300] [--batch-factors 1000] [--policy manual|default] [--fsync interval]`
pub async fn run(args: &crate::args::Args) -> Vec<Value> {
    let count: usize = args.parsed("--batches", 300);
    let size: usize = args.parsed("--batch-factors", 1000);
    let policy = args.value("--policy").unwrap_or_else(|| "manual".into());
    let fsync = args.value("--fsync").unwrap_or_else(|| "interval".into());
    // About 1.33 factors per pose in this generator: enough poses for `count` full chunks.
    let mut g = graph::manhattan(count * size * 3 / 4 + 10, 23);
    while g.edges.len() < count * size {
        g = graph::manhattan(g.guesses.len() * 11 / 10, 23);
    }
    g.edges.truncate(count * size);
    let top = g.edges.iter().map(|e| e.from.max(e.to)).max().unwrap_or(0);
    g.guesses.truncate(top + 1);
    let batches = graph::chunks(&g, size, "robot");
    let create = match policy.as_str() {
        "manual" => json!({"kind": "pose_graph_2d", "auto_optimize": {"policy": "manual"}}),
        _ => json!({"kind": "pose_graph_2d"}),
    };
    let mut factord = run_one(
        "ingest",
        create,
        &["--fsync", fsync.as_str()],
        &batches,
        g.guesses.len(),
    )
    .await;
    factord["scenario"] = json!("ingest");
    factord["system"] = json!("factord");
    factord["transport"] = json!("zenoh");
    factord["fsync"] = json!(fsync);
    factord["policy"] = json!(policy);
    factord["batch_factors"] = json!(size);
    factord["target_factors_per_s"] = json!(200_000);
    factord["target_met"] = json!(
        factord["factors_per_s"].as_f64().unwrap_or(0.0) >= 200_000.0 && factord["lost"] == 0
    );

    let echo = EchoPeer::start();
    let z = zenoh_peer(&[echo.zenoh.as_str()]).await;
    // Let the two peers connect before the clock starts.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let sent = publish_all(
        &z,
        "echo",
        "robot",
        &batches,
        Duration::from_secs(2),
        Duration::from_secs(10),
    )
    .await;
    let mut reference = stream_report(&sent, &batches);
    reference["scenario"] = json!("ingest");
    reference["system"] = json!("zenoh echo (reference)");
    reference["echo_peak_rss_mib"] = json!(echo.peak_rss_kib() as f64 / 1024.0);
    z.close().await.expect("zenoh closes");
    drop(echo);
    let ratio = factord["factors_per_s"].as_f64().unwrap_or(0.0)
        / reference["factors_per_s"].as_f64().unwrap_or(f64::NAN);
    factord["ratio_to_zenoh_echo"] = json!(ratio);
    vec![factord, reference]
}
