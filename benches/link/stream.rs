//! Scenario `stream`: a graph published at full rate over zenoh, pose by pose, numbered batches
//! with congestion control Block, into a fresh `factord serve` (journal on, default fsync and
//! auto-optimise policy): `input_M3500_g2o` and a generated Manhattan graph (50k poses by
//! default). Every batch must be covered by an ack (individual or cumulative) and applied once.

use std::sync::Arc;
use std::time::{Duration, Instant};

use serde_json::{json, Value};

use crate::acks::{self, Tracker};
use crate::graph;
use crate::proc::{http_get, http_post, metrics, zenoh_get, zenoh_peer, Server};

/// What publishing `batches` at full rate and waiting for their acks measured.
pub struct Sent {
    pub tracker: acks::Shared,
    /// From the first put until the last put returned / every batch was covered.
    pub put_seconds: f64,
    pub total_seconds: f64,
    /// Batches published again (go-back-N from the covered frontier after `resend_after`
    /// without progress; safe: repeats are answered as duplicates).
    pub resent: u64,
}

/// Publishes every batch on `<prefix>/in/batch` as fast as zenoh takes them (Block), then waits
/// until all are covered on `<prefix>/out/**`; a stall of `resend_after` resends from the
/// covered frontier; gives up after `give_up` without progress.
pub async fn publish_all(
    z: &zenoh::Session,
    prefix: &str,
    producer: &str,
    batches: &[(String, usize)],
    resend_after: Duration,
    give_up: Duration,
) -> Sent {
    let n = batches.len();
    let tracker = Tracker::new(producer, n);
    let wake = Arc::new(tokio::sync::Notify::new());
    let _sub = acks::subscribe(
        z,
        &format!("{prefix}/out/**"),
        tracker.clone(),
        wake.clone(),
    )
    .await;
    let publisher = z
        .declare_publisher(format!("{prefix}/in/batch"))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .expect("publisher");
    // Give the subscription time to reach the other side (as the repository's zenoh tests).
    tokio::time::sleep(Duration::from_millis(500)).await;
    let start = Instant::now();
    for (i, (body, _)) in batches.iter().enumerate() {
        tracker.lock().expect("not poisoned").sending(i as u64 + 1);
        publisher.put(body.clone()).await.expect("published");
    }
    let put_seconds = start.elapsed().as_secs_f64();
    let (mut resent, mut progress_at, mut last) = (0u64, Instant::now(), 0u64);
    loop {
        let notified = wake.notified();
        let (covered, frontier) = {
            let t = tracker.lock().expect("not poisoned");
            (t.covered, t.frontier())
        };
        if covered as usize >= n {
            break;
        }
        if covered > last {
            (last, progress_at) = (covered, Instant::now());
        }
        if progress_at.elapsed() > give_up {
            break;
        }
        if progress_at.elapsed() > resend_after {
            for (body, _) in batches.iter().skip(frontier as usize) {
                publisher.put(body.clone()).await.expect("published");
                resent += 1;
            }
            progress_at = Instant::now();
        }
        let _ = tokio::time::timeout(Duration::from_millis(100), notified).await;
    }
    let total_seconds = start.elapsed().as_secs_f64();
    Sent {
        tracker,
        put_seconds,
        total_seconds,
        resent,
    }
}

/// The part of a report every zenoh stream shares: counts, rates, latency and lag.
pub fn stream_report(sent: &Sent, batches: &[(String, usize)]) -> Value {
    let t = sent.tracker.lock().expect("not poisoned");
    let factors: usize = batches.iter().map(|b| b.1).sum();
    let bytes: usize = batches.iter().map(|b| b.0.len()).sum();
    let (individually, cumulatively) = t.split();
    let mut lat = t.latencies_ms();
    let (p50, p99, worst) = acks::summary(&mut lat);
    json!({
        "batches": batches.len(),
        "factors": factors,
        "payload_mb": bytes as f64 / 1e6,
        "covered": t.covered,
        "lost": batches.len() as u64 - t.covered,
        "acked_individually": individually,
        "covered_only_cumulatively": cumulatively,
        "duplicates": t.duplicates,
        "resent": sent.resent,
        "lagged_markers": t.lagged_total(),
        "lagged_by_key": t.lagged,
        "error_events": t.errors.len(),
        "first_errors": t.errors.iter().take(3).collect::<Vec<_>>(),
        "put_seconds": sent.put_seconds,
        "total_seconds": sent.total_seconds,
        "batches_per_s": batches.len() as f64 / sent.total_seconds,
        "factors_per_s": factors as f64 / sent.total_seconds,
        "mb_per_s": bytes as f64 / 1e6 / sent.total_seconds,
        "ack_p50_ms": p50,
        "ack_p99_ms": p99,
        "ack_worst_ms": worst,
    })
}

/// A fresh server, a session `name` created over HTTP with `create` fields, `batches` streamed
/// over zenoh; then the server's own counts and peak RSS.
pub async fn run_one(
    name: &str,
    create: Value,
    flags: &[&str],
    batches: &[(String, usize)],
    poses: usize,
) -> Value {
    let (server, dir) = Server::single(flags);
    let c = reqwest::Client::new();
    let mut body = create;
    body["session"] = json!(name);
    let (status, answer) = http_post(&c, &server.url("/v1/sessions"), &body).await;
    assert_eq!(status, 201, "create {name}: {answer}");
    let z = zenoh_peer(&[server.zenoh.as_str()]).await;
    zenoh_get(&z, &format!("factord/{name}/estimate"), None)
        .await
        .expect("the session's queryable answers");
    let perf = crate::proc::Perf::attach(server.pid());
    let jitter = crate::jitter::Jitter::start();
    let cpu_before = server.cpu_seconds();
    let sent = publish_all(
        &z,
        &format!("factord/{name}"),
        "robot",
        batches,
        Duration::from_secs(2),
        Duration::from_secs(30),
    )
    .await;
    drop(perf);
    let server_cpu = server.cpu_seconds() - cpu_before;
    let mut report = stream_report(&sent, batches);
    report["server_cpu_seconds"] = json!(server_cpu);
    report["machine_wakeup_jitter"] = jitter.finish();
    let (_, info) = http_get(&c, &server.url(&format!("/v1/sessions/{name}"))).await;
    let (_, status) = http_get(
        &c,
        &server.url(&format!("/v1/sessions/{name}/producers/robot")),
    )
    .await;
    let factors = report["factors"].as_u64().unwrap_or(0);
    report["server_sequence"] = info["sequence"].clone();
    report["server_num_factors"] = info["num_factors"].clone();
    report["server_num_variables"] = info["num_variables"].clone();
    report["server_solves"] = info["solves"].clone();
    report["server_accepted_through"] = status["accepted_through"].clone();
    report["applied_once"] = json!(
        info["num_factors"].as_u64() == Some(factors)
            && info["num_variables"].as_u64() == Some(poses as u64)
            && status["accepted_through"].as_u64() == Some(batches.len() as u64)
    );
    report["server_peak_rss_mib"] = json!(server.peak_rss_kib() as f64 / 1024.0);
    report["server_metrics"] =
        json!(metrics(&c, &server, &["lagged", "skipped", "journal_fsync"]).await);
    report["server_warnings"] = json!(server.warnings().into_iter().take(5).collect::<Vec<_>>());
    z.close().await.expect("zenoh closes");
    drop(server);
    let _ = std::fs::remove_dir_all(&dir);
    report
}

/// `stream [--poses 50000] [--only m3500|manhattan]`
pub async fn run(args: &crate::args::Args) -> Vec<Value> {
    let poses: usize = args.parsed("--poses", 50_000);
    let only = args.value("--only");
    let mut out = Vec::new();
    if only.as_deref() != Some("manhattan") {
        match graph::data_file("2d/carlone/input_M3500_g2o.g2o") {
            Ok(path) => {
                let g = graph::parse_g2o_se2(&std::fs::read_to_string(path).expect("readable"));
                let batches = graph::per_pose(&g, "robot");
                let mut r = run_one(
                    "m3500",
                    json!({"kind": "pose_graph_2d"}),
                    &[],
                    &batches,
                    g.guesses.len(),
                )
                .await;
                r["graph"] = json!("input_M3500_g2o");
                out.push(r);
            }
            Err(why) => {
                eprintln!("stream: skipping input_M3500_g2o: {why}");
                out.push(json!({"graph": "input_M3500_g2o", "skipped": why}));
            }
        }
    }
    if only.as_deref() != Some("m3500") {
        let g = graph::manhattan(poses, 17);
        let batches = graph::per_pose(&g, "robot");
        let mut r = run_one(
            "manhattan",
            json!({"kind": "pose_graph_2d"}),
            &[],
            &batches,
            poses,
        )
        .await;
        r["graph"] = json!(format!("manhattan_{poses}"));
        out.push(r);
    }
    for r in &mut out {
        r["scenario"] = json!("stream");
        r["transport"] = json!("zenoh");
        r["fsync"] = json!("always (default)");
    }
    out
}
