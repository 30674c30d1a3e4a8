//! Load and garbage, bounded and on loopback only: 100 sessions stream pose graphs at once (half
//! over HTTP, half over zenoh's rpc), pose by pose with every-batch solving and the journal's
//! fsync, while garbage clients send malformed, mistyped and misaddressed input over both.
//!
//! Reports sessions, factors/s sustained, ack latency percentiles per transport, the server's
//! peak RSS, the garbage rejected (all must be 4xx) and errors seen by the good clients (must
//! be 0).
//!
//! `cargo bench --bench load -- [--sessions 100] [--poses 200] [--seconds 120] [--fsync always]`

#[path = "../../tests/common/mod.rs"]
mod common;

#[path = "../args.rs"]
mod args;
#[path = "../stats.rs"]
mod stats;

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use common::server::{g2o_batches, zenoh_get, zenoh_peer, TestServer};
use serde_json::{json, Value};

#[derive(Default)]
struct Tally {
    http_latency: Mutex<Vec<f64>>,
    zenoh_latency: Mutex<Vec<f64>>,
    factors: AtomicU64,
    good_errors: Mutex<Vec<String>>,
    garbage_sent: AtomicU64,
    garbage_rejected: AtomicU64,
    garbage_unexpected: Mutex<Vec<String>>,
}

impl Tally {
    /// A garbage HTTP request's answer: a 4xx is the intended refusal, anything else is noted.
    fn garbage_answered(&self, answer: reqwest::Result<reqwest::StatusCode>, what: &str) {
        let unexpected = match answer {
            Ok(status) if status.is_client_error() => {
                self.garbage_rejected.fetch_add(1, Ordering::Relaxed);
                return;
            }
            Ok(status) => format!("HTTP {status} for {what}"),
            Err(e) => format!("HTTP: {e}"),
        };
        self.garbage_unexpected.lock().unwrap().push(unexpected);
    }
}

fn peak_rss_kib(pid: u32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .unwrap_or_default()
        .lines()
        .find(|l| l.starts_with("VmHWM:"))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(0)
}

fn factors_in(batch: &Value) -> u64 {
    batch["factors"].as_array().map_or(0, |f| f.len() as u64)
}

async fn http_client(url: String, batches: Vec<Value>, tally: Arc<Tally>, deadline: Instant) {
    let c = reqwest::Client::new();
    for b in batches {
        if Instant::now() > deadline {
            return;
        }
        let t = Instant::now();
        match c.post(&url).json(&b).send().await {
            Ok(r) if r.status() == 200 => {
                tally
                    .http_latency
                    .lock()
                    .unwrap()
                    .push(t.elapsed().as_secs_f64());
                tally.factors.fetch_add(factors_in(&b), Ordering::Relaxed);
            }
            Ok(r) => {
                let status = r.status();
                let body = r.text().await.unwrap_or_default();
                tally
                    .good_errors
                    .lock()
                    .unwrap()
                    .push(format!("HTTP {status}: {body}"));
            }
            Err(e) => tally.good_errors.lock().unwrap().push(format!("HTTP: {e}")),
        }
    }
}

async fn zenoh_client(
    z: zenoh::Session,
    session: String,
    batches: Vec<Value>,
    tally: Arc<Tally>,
    deadline: Instant,
) {
    for b in batches {
        if Instant::now() > deadline {
            return;
        }
        let t = Instant::now();
        let command = json!({"op": "apply_batch", "session": session, "batch": b});
        match zenoh_get(&z, "factord/rpc", Some(&command)).await {
            Ok(_) => {
                tally
                    .zenoh_latency
                    .lock()
                    .unwrap()
                    .push(t.elapsed().as_secs_f64());
                tally.factors.fetch_add(factors_in(&b), Ordering::Relaxed);
            }
            Err(e) => tally
                .good_errors
                .lock()
                .unwrap()
                .push(format!("zenoh: {e}")),
        }
    }
}

/// Malformed, mistyped and misaddressed input, over both transports, until `deadline`.
async fn garbage_client(
    s_url: String,
    z: zenoh::Session,
    sessions: Vec<String>,
    tally: Arc<Tally>,
    deadline: Instant,
    seed: u64,
) {
    let c = reqwest::Client::new();
    let mut rng = seed | 1;
    let mut next = move || {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        rng
    };
    let garbage: Vec<String> = vec![
        "{".into(),
        "not json at all".into(),
        json!({"variables": [{"key": 1, "kind": "se3", "value": [0, 0, 0]}]}).to_string(),
        json!({"variables": [{"key": "one", "kind": "se2"}]}).to_string(),
        json!({"factors": [{"type": "between_se2", "keys": [999_999, 999_998], "measurement": [1, 0, 0], "sigmas": [1, 1, 1]}]}).to_string(),
        json!({"factors": [{"type": "between_se2", "keys": [0, 1], "measurement": [1, 0], "sigmas": [1, 1, 1]}]}).to_string(),
        json!({"factors": [{"type": "between_se2", "keys": [0, 1], "measurement": [1, 0, 0], "information": [1, 0, 0, -1, 0, 1]}]}).to_string(),
        json!({"variables": [{"key": 0, "kind": "se2", "value": [0, 0, 0]}]}).to_string(),
        json!({"remove_factors": [123_456_789]}).to_string(),
        json!({"unexpected": true}).to_string(),
    ];
    while Instant::now() < deadline {
        let session = &sessions[(next() % sessions.len() as u64) as usize];
        let body = &garbage[(next() % garbage.len() as u64) as usize];
        tally.garbage_sent.fetch_add(1, Ordering::Relaxed);
        match next() % 3 {
            0 => {
                let url = format!("{s_url}/v1/sessions/{session}/batches");
                let answer = c
                    .post(&url)
                    .header("content-type", "application/json")
                    .body(body.clone())
                    .send()
                    .await
                    .map(|r| r.status());
                tally.garbage_answered(answer, body);
            }
            1 => {
                // To a session that does not exist: 404, or 400 when the body is refused before
                // the session is looked up.
                let url = format!("{s_url}/v1/sessions/nobody-{}/batches", next() % 1000);
                let answer = c
                    .post(&url)
                    .header("content-type", "application/json")
                    .body(body.clone())
                    .send()
                    .await;
                tally.garbage_answered(answer.map(|r| r.status()), "a missing session");
            }
            _ => {
                let command = match serde_json::from_str::<Value>(body) {
                    Ok(batch) => json!({"op": "apply_batch", "session": session, "batch": batch}),
                    Err(_) => json!({"op": "apply_batch", "session": session, "batch": body}),
                };
                match zenoh_get(&z, "factord/rpc", Some(&command)).await {
                    Err(e)
                        if e["error"]["status"]
                            .as_u64()
                            .is_some_and(|s| (400..500).contains(&s)) =>
                    {
                        tally.garbage_rejected.fetch_add(1, Ordering::Relaxed);
                    }
                    Err(e) => tally
                        .garbage_unexpected
                        .lock()
                        .unwrap()
                        .push(format!("zenoh: {e}")),
                    // A valid variable at a free key can be accepted: garbage that is not.
                    Ok(_) => {
                        tally.garbage_rejected.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
        }
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
}

fn main() {
    let args = args::Args::from_env();
    let sessions: usize = args.parsed("--sessions", 100);
    let poses: usize = args.parsed("--poses", 200);
    let seconds: u64 = args.parsed("--seconds", 120);
    let fsync = args.value("--fsync").unwrap_or_else(|| "always".into());
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .unwrap();
    let report = runtime.block_on(async {
        let s = TestServer::start(&["--log", "warn", "--fsync", fsync.as_str()]);
        let tally = Arc::new(Tally::default());
        let c = reqwest::Client::new();
        let names: Vec<String> = (0..sessions).map(|i| format!("load{i}")).collect();
        for name in &names {
            let r = c.post(s.url("/v1/sessions"))
                .json(&json!({"session": name, "kind": "pose_graph_2d"}))
                .send().await.unwrap();
            assert_eq!(r.status(), 201);
        }
        let mut peers = Vec::new();
        for _ in 0..4 {
            peers.push(zenoh_peer(&s.zenoh).await);
        }
        let deadline = Instant::now() + Duration::from_secs(seconds);
        let start = Instant::now();
        let mut tasks = Vec::new();
        for (i, name) in names.iter().enumerate() {
            let batches = g2o_batches(&common::synthetic_manhattan(poses, i as u64 + 1));
            let tally = Arc::clone(&tally);
            if i % 2 == 0 {
                let url = s.url(&format!("/v1/sessions/{name}/batches"));
                tasks.push(tokio::spawn(http_client(url, batches, tally, deadline)));
            } else {
                let z = peers[i % peers.len()].clone();
                tasks.push(tokio::spawn(zenoh_client(z, name.clone(), batches, tally, deadline)));
            }
        }
        let mut garbage = Vec::new();
        let good_done = Arc::new(std::sync::atomic::AtomicBool::new(false));
        for g in 0..5u64 {
            let (url, z, names, tally) = (s.http.clone(), peers[0].clone(), names.clone(), Arc::clone(&tally));
            let done = Arc::clone(&good_done);
            garbage.push(tokio::spawn(async move {
                // Garbage for as long as the good clients stream.
                let until = deadline;
                let task = tokio::spawn(garbage_client(url, z, names, tally, until, 0x5eed + g));
                while !done.load(Ordering::Relaxed) && Instant::now() < until {
                    tokio::time::sleep(Duration::from_millis(20)).await;
                }
                task.abort();
            }));
        }
        for t in tasks {
            t.await.unwrap();
        }
        let streamed = start.elapsed().as_secs_f64();
        good_done.store(true, Ordering::Relaxed);
        for g in garbage {
            let _ = g.await;
        }
        // Every session holds every pose it was sent.
        let mut incomplete = 0;
        for name in &names {
            let v: Value = c.get(s.url(&format!("/v1/sessions/{name}"))).send().await.unwrap().json().await.unwrap();
            if v["num_variables"].as_u64() != Some(poses as u64) {
                incomplete += 1;
            }
        }
        let rss = peak_rss_kib(s.pid());
        let metrics = c.get(s.url("/metrics")).send().await.unwrap().text().await.unwrap();
        for z in peers {
            z.close().await.unwrap();
        }
        s.assert_no_panic();
        let mut http = tally.http_latency.lock().unwrap().clone();
        let mut zen = tally.zenoh_latency.lock().unwrap().clone();
        http.sort_by(f64::total_cmp);
        zen.sort_by(f64::total_cmp);
        let rejected_lines: Vec<&str> = metrics.lines().filter(|l| l.starts_with("factord_rejected_inputs_total{")).collect();
        json!({
            "sessions": sessions, "poses_per_session": poses, "fsync": fsync,
            "stream_seconds": streamed,
            "factors_acknowledged": tally.factors.load(Ordering::Relaxed),
            "factors_per_second": tally.factors.load(Ordering::Relaxed) as f64 / streamed,
            "batches_acknowledged": http.len() + zen.len(),
            "http_ack_ms": {"p50": 1e3 * stats::percentile(&http, 0.5), "p99": 1e3 * stats::percentile(&http, 0.99), "max": 1e3 * stats::percentile(&http, 1.0)},
            "zenoh_ack_ms": {"p50": 1e3 * stats::percentile(&zen, 0.5), "p99": 1e3 * stats::percentile(&zen, 0.99), "max": 1e3 * stats::percentile(&zen, 1.0)},
            "peak_rss_mib": rss as f64 / 1024.0,
            "sessions_incomplete": incomplete,
            "good_client_errors": *tally.good_errors.lock().unwrap(),
            "garbage_sent": tally.garbage_sent.load(Ordering::Relaxed),
            "garbage_rejected_4xx": tally.garbage_rejected.load(Ordering::Relaxed),
            "garbage_unexpected": *tally.garbage_unexpected.lock().unwrap(),
            "server_rejections_by_reason": rejected_lines,
        })
    });
    println!("{}", serde_json::to_string_pretty(&report).unwrap());
}
