//! Service benchmarks against the real `factord serve` binary over real sockets:
//!
//! 1. `job`: an HTTP batch job of a g2o file, client-measured wall time (upload, solve, JSON
//!    answer received), against the wall time of `factord solve` on the same file (process
//!    start, load, solve, exit). Rounds interleave the two.
//! 2. `ingest`: factors/s of a whole graph (its factors ten times) published over zenoh in
//!    batches (manual policy, so
//!    this is validation and bookkeeping, not solving), timed until the last batch's ack.
//! 3. `latency`: the graph streamed over zenoh pose by pose, each pose published once the
//!    previous one's estimate is available; publish-to-estimate latency per pose (ack with
//!    `reflected`, or the summary of the solve that includes it).
//!
//! `cargo bench --bench service -- <file.g2o> [--rounds N] [--json out.json] [--fsync always|interval|never]
//! [--ingest-only]`

#[path = "../../tests/common/mod.rs"]
mod common;

#[path = "../args.rs"]
mod args;
#[path = "../stats.rs"]
mod stats;

use std::process::Command;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use common::server::{g2o_batches, zenoh_get, zenoh_peer, TestServer};
use serde_json::{json, Value};

async fn rpc(z: &zenoh::Session, command: Value) -> Value {
    zenoh_get(z, "factord/rpc", Some(&command))
        .await
        .expect("rpc succeeds")
}

/// Events of one session topic, timestamped on arrival, and a wake-up for whoever waits.
#[derive(Default)]
struct Events {
    list: Mutex<Vec<(Instant, Value)>>,
    arrived: tokio::sync::Notify,
}
type Inbox = Arc<Events>;

async fn subscribe(z: &zenoh::Session, key: &str, inbox: Inbox) -> zenoh::pubsub::Subscriber<()> {
    z.declare_subscriber(key)
        .callback(move |sample| {
            let v: Value = serde_json::from_slice(&sample.payload().to_bytes()).unwrap();
            inbox.list.lock().unwrap().push((Instant::now(), v));
            inbox.arrived.notify_waiters();
        })
        .await
        .unwrap()
}

async fn job_vs_cli(s: &TestServer, file: &str, rounds: usize) -> Value {
    let body = std::fs::read(file).unwrap();
    let client = reqwest::Client::new();
    let (mut http, mut cli) = (Vec::new(), Vec::new());
    let mut chi2 = (0.0, 0.0);
    for _ in 0..rounds {
        let t = Instant::now();
        let out = Command::new(env!("CARGO_BIN_EXE_factord"))
            .args([
                "solve",
                file,
                "--quiet",
                "--summary-json",
                "/tmp/factord-bench-summary.json",
            ])
            .output()
            .unwrap();
        cli.push(t.elapsed().as_secs_f64());
        assert!(out.status.success());
        let summary: Value = serde_json::from_str(
            &std::fs::read_to_string("/tmp/factord-bench-summary.json").unwrap(),
        )
        .unwrap();
        chi2.0 = summary["final_chi2"].as_f64().unwrap();

        let t = Instant::now();
        let resp = client
            .post(s.url("/v1/jobs"))
            .body(body.clone())
            .send()
            .await
            .unwrap();
        let text = resp.text().await.unwrap();
        http.push(t.elapsed().as_secs_f64());
        let v: Value = serde_json::from_str(&text).unwrap();
        chi2.1 = v["summary"]["final_chi2"].as_f64().unwrap();
    }
    let (h, c) = (stats::median(&mut http), stats::median(&mut cli));
    json!({"http_job_seconds_median": h, "cli_solve_seconds_median": c, "ratio": h / c,
           "http_runs": http, "cli_runs": cli, "final_chi2_cli": chi2.0, "final_chi2_http": chi2.1})
}

async fn ingest(s: &TestServer, z: &zenoh::Session, text: &str, batch_factors: usize) -> Value {
    let session = format!("ingest{batch_factors}");
    rpc(
        z,
        json!({"op": "create_session", "session": session, "kind": "pose_graph_2d",
                  "auto_optimize": {"policy": "manual"}}),
    )
    .await;
    let mut variables = Vec::new();
    let mut factors = Vec::new();
    for b in g2o_batches(text) {
        for mut v in b["variables"].as_array().unwrap().clone() {
            if v.get("value").is_none() {
                v["value"] = json!([0.0, 0.0, 0.0]);
            }
            variables.push(v);
        }
        factors.extend(b["factors"].as_array().unwrap().clone());
    }
    // The graph's factors ten times over (duplicates are valid factors), for a stable rate.
    let factors: Vec<Value> = std::iter::repeat_n(factors, 10).flatten().collect();
    let mut batches = vec![json!({"variables": variables}).to_string()];
    for chunk in factors.chunks(batch_factors) {
        batches.push(json!({"factors": chunk}).to_string());
    }
    let acks: Inbox = Default::default();
    let _sub = subscribe(z, &format!("factord/{session}/out/acks"), acks.clone()).await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let publisher = z
        .declare_publisher(format!("factord/{session}/in/batch"))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .unwrap();
    let last = batches.len() as u64;
    let start = Instant::now();
    for b in batches {
        publisher.put(b).await.unwrap();
    }
    let published = start.elapsed().as_secs_f64();
    let deadline = Instant::now() + Duration::from_secs(120);
    let done = loop {
        let arrived = acks.arrived.notified();
        if let Some((t, _)) = acks
            .list
            .lock()
            .unwrap()
            .iter()
            .find(|(_, v)| v["sequence"] == last)
        {
            break *t;
        }
        // The ack stream may skip events under load (a lagging subscriber); the session's
        // sequence is authoritative.
        let stats: Value = reqwest::get(s.url(&format!("/v1/sessions/{session}")))
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        if stats["sequence"] == last {
            break Instant::now();
        }
        assert!(Instant::now() < deadline, "ingest did not finish");
        let _ = tokio::time::timeout(Duration::from_millis(20), arrived).await;
    };
    let seconds = (done - start).as_secs_f64();
    let c = reqwest::Client::new();
    let stats: Value = c
        .get(s.url(&format!("/v1/sessions/{session}")))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(
        stats["num_factors"].as_u64().unwrap() as usize,
        factors.len()
    );
    json!({"batch_factors": batch_factors, "factors": factors.len(), "seconds": seconds,
           "publish_seconds": published, "factors_per_second": factors.len() as f64 / seconds})
}

async fn latency(z: &zenoh::Session, text: &str) -> Value {
    rpc(
        z,
        json!({"op": "create_session", "session": "stream", "kind": "pose_graph_2d"}),
    )
    .await;
    let acks: Inbox = Default::default();
    let summaries: Inbox = Default::default();
    let _a = subscribe(z, "factord/stream/out/acks", acks.clone()).await;
    let _s = subscribe(z, "factord/stream/out/summary", summaries.clone()).await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let publisher = z
        .declare_publisher("factord/stream/in/batch")
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .unwrap();
    let batches = g2o_batches(text);
    let mut latencies = Vec::with_capacity(batches.len());
    let start = Instant::now();
    for (i, b) in batches.iter().enumerate() {
        let sequence = i as u64 + 1;
        let t = Instant::now();
        publisher.put(b.to_string()).await.unwrap();
        let deadline = Instant::now() + Duration::from_secs(60);
        let available = loop {
            // Register for wake-ups before looking, so no arrival is missed in between.
            let (ack_arrived, summary_arrived) =
                (acks.arrived.notified(), summaries.arrived.notified());
            let reflected = acks
                .list
                .lock()
                .unwrap()
                .last()
                .filter(|(_, v)| v["sequence"] == sequence && v["reflected"] == true)
                .map(|(t, _)| *t);
            // Summaries arrive in sequence order: the latest is the one that may cover this pose.
            let solved = summaries
                .list
                .lock()
                .unwrap()
                .last()
                .filter(|(_, v)| v["sequence"].as_u64().unwrap() >= sequence)
                .map(|(t, _)| *t);
            if let Some(at) = reflected.or(solved) {
                break at;
            }
            assert!(Instant::now() < deadline, "no estimate for pose {i}");
            let _ = tokio::time::timeout(Duration::from_millis(50), async {
                tokio::select! {
                    _ = ack_arrived => {},
                    _ = summary_arrived => {},
                }
            })
            .await;
        };
        latencies.push((available - t).as_secs_f64() * 1e3);
    }
    let total = start.elapsed().as_secs_f64();
    let final_chi2 = rpc(z, json!({"op": "get_stats", "session": "stream"})).await["chi2"].clone();
    let mean = latencies.iter().sum::<f64>() / latencies.len() as f64;
    latencies.sort_by(f64::total_cmp);
    json!({"poses": latencies.len(), "total_seconds": total, "mean_ms": mean,
           "p50_ms": stats::percentile(&latencies, 0.5), "p90_ms": stats::percentile(&latencies, 0.9),
           "p99_ms": stats::percentile(&latencies, 0.99), "max_ms": latencies.last(),
           "final_chi2": final_chi2})
}

fn main() {
    let args = args::Args::from_env();
    let file = args.first("usage: service <file.g2o> [--rounds N] [--json out]");
    let rounds: usize = args.parsed("--rounds", 5);
    let text = std::fs::read_to_string(&file).unwrap();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .unwrap();
    let report = runtime.block_on(async {
        // `--fsync always|interval|never`: the journal policy of the server under test.
        let fsync = args.value("--fsync").unwrap_or_else(|| "always".into());
        let s = TestServer::start(&["--log", "warn", "--fsync", fsync.as_str()]);
        let only_ingest = args.has("--ingest-only");
        let job = if only_ingest {
            Value::Null
        } else {
            job_vs_cli(&s, &file, rounds).await
        };
        let z = zenoh_peer(&s.zenoh).await;
        let mut ingest_runs = Vec::new();
        for batch in [1, 100, 1000] {
            ingest_runs.push(ingest(&s, &z, &text, batch).await);
        }
        let stream = if only_ingest {
            Value::Null
        } else {
            latency(&z, &text).await
        };
        z.close().await.unwrap();
        s.assert_no_panic();
        json!({"dataset": file, "fsync": fsync, "http_job_vs_cli": job, "zenoh_ingest": ingest_runs,
               "zenoh_publish_to_estimate": stream})
    });
    println!("{}", serde_json::to_string_pretty(&report).unwrap());
    if let Some(out) = args.value("--json") {
        std::fs::write(out, report.to_string()).unwrap();
    }
}
