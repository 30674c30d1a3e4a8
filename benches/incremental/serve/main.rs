//! A g2o pose graph (2D or 3D) streamed pose by pose into the real `factord serve` binary over
//! real sockets, the durable journal on (fsync always by default), one session: the client's
//! view of every update, for issue 16's acceptance (driven by `acceptance.py`, next to this).
//!
//! `cargo bench --bench incremental_serve -- <file.g2o> --transport http|zenoh [--limit N]
//! [--json out.json] [--dump-latencies out.txt] [--dump-server out.jsonl]
//! [--fsync always|interval|never] [--poses json|binary|none] [--max-update-ms N]`
//!
//! `--max-update-ms N` gives the session a latency budget (provisional answers count as the
//! answer: over zenoh, an estimate of the batch on `bin/poses`).
//!
//! GTSAM's landmark text (`victoria_park.txt`) streams as `landmarks.rs` says, against
//! `isam2_landmarks.py`.
//!
//! Protocol (the one of `isam2_stream.py` and `incremental_stream`): batch k holds pose k with
//! every edge whose later end is k (`tests/common` `g2o_batches`: a pose with an odometry edge
//! from k−1 is sent without a value, the server predicts it); batch k+1 is sent once the
//! estimate reflects batch k.
//! - `http`: `POST /v1/sessions/<s>/batches?wait=true`; latency = request sent → answer read.
//! - `zenoh`: publish on `factord/<s>/in/batch`; latency = publish → arrival of the ack that
//!   says `reflected` or of the summary of a solve that includes it. The client subscribes to
//!   its poses as a robot does: `--poses json` (the default) on `out/poses`, `binary` on
//!   `bin/poses`, `none` (or `--without-poses`) not at all, to measure what they cost.
//!
//! Batches are serialised before the clock starts (as isam2_stream.py parses the file first).
//! After the stream (not timed): the estimate is read over HTTP and its chi2 compared with the
//! batch optimum of the same (truncated) graph (`optimum.rs`), and the server's peak resident
//! memory is read from `/proc/<pid>/status` (VmHWM). Each run starts a fresh server, so the peak
//! is that of this stream; so are the CPU seconds the server and this client (its zenoh threads
//! included) spent during the stream (`/proc/<pid>/stat`), steadier than wall time on a shared
//! machine. Prints one JSON object; `--dump-latencies` writes one latency (ms)
//! per line, in stream order; `--dump-server` the server's view of every solve
//! (`server_view.rs`). The JSON carries the server's latency histograms (fsync, solve, landing,
//! provisional answers) from its `/metrics`.
//!
//! `--memory-every N` (HTTP) records the server's peak resident memory so far and the session's
//! `memory_bytes` every N updates (`memory_at`); `--restart` then kills the server with SIGKILL
//! once it is idle and starts it again on its state directory, and reports how long until the
//! session answers with every variable (`restart_seconds`) and the new server's peak memory.

#[path = "../../../tests/common/mod.rs"]
mod common;

#[path = "../../args.rs"]
mod args;
#[path = "../../stats.rs"]
mod stats;

mod http;
mod landmarks;
mod optimum;
mod server_view;
mod zenoh_stream;

use std::collections::HashSet;
use std::time::Duration;

use serde_json::{json, Value};

use common::server::{create, g2o_batches, get, TestServer};

/// One stream's client-side measurements.
pub struct Streamed {
    /// Per update, in stream order.
    pub latencies_ms: Vec<f64>,
    pub wall_seconds: f64,
    /// Updates whose availability was learnt by polling the session (see each transport).
    pub fallbacks: usize,
    /// Bytes and samples the poses subscriber received (zenoh with `--poses json|binary`).
    pub poses_received: Option<(u64, u64)>,
    /// `--memory-every N` (HTTP): the server's memory every N updates.
    pub memory: Vec<MemoryAt>,
}

/// The server's memory after `updates` updates: its peak resident set so far and the
/// session's own estimate (`memory_bytes`).
#[derive(serde::Serialize)]
pub struct MemoryAt {
    pub updates: usize,
    pub peak_rss_kb: Option<u64>,
    pub session_memory_bytes: Option<u64>,
}

/// A field of `/proc/<pid>/status` in kB (`VmHWM`: peak resident set).
fn proc_status_kb(pid: u32, field: &str) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.starts_with(field))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// CPU seconds (user + system) process `pid` (or `self`) has used so far.
fn cpu_seconds(pid: &str) -> Option<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // After the command name (in parentheses, which may hold spaces): state is field 3, utime
    // and stime are fields 14 and 15.
    let fields: Vec<&str> = stat[stat.rfind(')')? + 2..].split(' ').collect();
    let ticks: f64 = fields[11].parse::<f64>().ok()? + fields[12].parse::<f64>().ok()?;
    // SAFETY: sysconf only reads a configuration value.
    let per_second = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    (per_second > 0).then(|| ticks / per_second as f64)
}

/// CPU seconds the server and this client (zenoh's threads included) spent during the stream:
/// on 2 cores the two share, what either spends delays the other.
#[derive(Clone, Copy, Default)]
struct CpuUse {
    server: Option<f64>,
    client: Option<f64>,
}

impl CpuUse {
    fn now(server_pid: u32) -> Self {
        Self {
            server: cpu_seconds(&server_pid.to_string()),
            client: cpu_seconds("self"),
        }
    }

    fn since(self, start: Self) -> Self {
        let minus = |a: Option<f64>, b: Option<f64>| Some(a? - b?);
        Self {
            server: minus(self.server, start.server),
            client: minus(self.client, start.client),
        }
    }
}

fn main() {
    let args = args::Args::from_env();
    let usage = "usage: incremental_serve <file.g2o> --transport http|zenoh [--limit N] \
                 [--json out] [--dump-latencies out] [--dump-server out] \
                 [--fsync always|interval|never] [--poses json|binary|none] \
                 [--max-update-ms N] [--memory-every N] [--restart]";
    let path = args.first(usage);
    let transport = args
        .value("--transport")
        .unwrap_or_else(|| panic!("{usage}"));
    assert!(
        transport == "http" || transport == "zenoh",
        "--transport http|zenoh"
    );
    let limit: usize = args.parsed("--limit", usize::MAX);
    let fsync = args.value("--fsync").unwrap_or_else(|| "always".into());
    let poses = match args.has("--without-poses") {
        true => zenoh_stream::Poses::None,
        false => match args.value("--poses").as_deref() {
            None | Some("json") => zenoh_stream::Poses::Json,
            Some("binary") => zenoh_stream::Poses::Binary,
            Some("none") => zenoh_stream::Poses::None,
            Some(other) => panic!("--poses json|binary|none, not {other}"),
        },
    };
    let max_update_ms: Option<u64> = args.value("--max-update-ms").map(|v| {
        v.parse()
            .unwrap_or_else(|_| panic!("--max-update-ms N, not {v}"))
    });
    let memory_every: Option<usize> = args.value("--memory-every").map(|v| {
        v.parse()
            .unwrap_or_else(|_| panic!("--memory-every N, not {v}"))
    });
    let restart = args.has("--restart");
    let text = std::fs::read_to_string(&path).expect("readable graph");

    let mut batches = if landmarks::is_gtsam_text(&text) {
        landmarks::batches(&text, &path)
    } else {
        g2o_batches(&text)
    };
    batches.truncate(limit);
    let kept: HashSet<u64> = batches
        .iter()
        .flat_map(|b| b["variables"].as_array().expect("variables").clone())
        .map(|v| v["key"].as_u64().expect("key"))
        .collect();
    let kind = match batches[0]["variables"][0]["kind"].as_str() {
        Some("se3") => "pose_graph_3d",
        _ => "pose_graph_2d",
    };
    let bodies: Vec<String> = batches.iter().map(Value::to_string).collect();
    drop(batches);

    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("tokio runtime");
    let dump_server = args.value("--dump-server");
    let (
        streamed,
        cpu,
        estimate,
        idle_estimate,
        idle_seconds,
        stats,
        peak_kb,
        rss_kb,
        histograms,
        restarted,
    ) = runtime.block_on(async {
        let s = TestServer::start(&["--log", "warn", "--fsync", fsync.as_str()]);
        let c = common::server::client();
        let session = "stream";
        let mut request = json!({"session": session, "kind": kind});
        if let Some(budget) = max_update_ms {
            request["max_update_ms"] = json!(budget);
        }
        create(&c, &s, &request).await;
        let view = match &dump_server {
            Some(out) => Some((
                server_view::ServerView::listen(&s.zenoh, session).await,
                out,
            )),
            None => None,
        };
        let started = std::time::Instant::now();
        let cpu_start = CpuUse::now(s.pid());
        let streamed = match transport.as_str() {
            "http" => http::stream(&s, session, &bodies, memory_every).await,
            _ => {
                let (_, info) = get(&c, &s.url(&format!("/v1/sessions/{session}"))).await;
                let base = info["sequence"].as_u64().expect("sequence");
                let budget = max_update_ms.is_some();
                zenoh_stream::stream(&s, session, base, &bodies, poses, budget).await
            }
        };
        let cpu = CpuUse::now(s.pid()).since(cpu_start);
        let peak_kb = proc_status_kb(s.pid(), "VmHWM");
        let rss_kb = proc_status_kb(s.pid(), "VmRSS");
        let (status, estimate) = get(&c, &s.url(&format!("/v1/sessions/{session}/estimate"))).await;
        assert_eq!(status, 200, "{estimate}");
        // Then idle: the session polishes its estimate; wait until it says it converged.
        let idle = std::time::Instant::now();
        let mut stats = serde_json::Value::Null;
        while idle.elapsed() < Duration::from_secs(60) {
            stats = get(&c, &s.url(&format!("/v1/sessions/{session}"))).await.1;
            if stats["converged"] == true {
                break;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        let idle_seconds = idle.elapsed().as_secs_f64();
        let (status, idle_estimate) =
            get(&c, &s.url(&format!("/v1/sessions/{session}/estimate"))).await;
        assert_eq!(status, 200, "{idle_estimate}");
        // The server's view, the idle polish included.
        if let Some((view, out)) = &view {
            std::fs::write(out, view.lines(started)).expect("writable --dump-server");
        }
        let metrics = c.get(s.url("/metrics")).send().await.expect("metrics");
        let histograms = server_view::histograms(&metrics.text().await.expect("metrics text"));
        s.assert_no_panic();
        let state_dir = s.state_dir.clone();
        let restarted = match restart {
            true => {
                Some(restart_after_kill(s, session, &fsync, stats["num_variables"].clone()).await)
            }
            false => {
                let _ = s.terminate(Duration::from_secs(10));
                None
            }
        };
        let _ = std::fs::remove_dir_all(&state_dir);
        let _ = std::fs::remove_file(state_dir.with_extension("stderr"));
        (
            streamed,
            cpu,
            estimate,
            idle_estimate,
            idle_seconds,
            stats,
            peak_kb,
            rss_kb,
            histograms,
            restarted,
        )
    });

    let truncated = optimum::restrict(&text, &kept);
    let chi2 = optimum::compare(&truncated, &path, &estimate);
    let idle_chi2 = optimum::compare(&truncated, &path, &idle_estimate);

    let latencies = streamed.latencies_ms;
    let mut sorted = latencies.clone();
    sorted.sort_by(f64::total_cmp);
    let mut report = json!({
        "system": "factord",
        "transport": transport,
        "poses": match transport.as_str() {
            "zenoh" => json!(poses.name()),
            _ => Value::Null,
        },
        "fsync": fsync,
        "dataset": std::path::Path::new(&path).file_stem().map(|s| s.to_string_lossy()),
        "file": path,
        "limit": (limit != usize::MAX).then_some(limit),
        "steps": latencies.len(),
        "total_seconds": latencies.iter().sum::<f64>() / 1e3,
        "wall_seconds": streamed.wall_seconds,
        "mean_ms": latencies.iter().sum::<f64>() / latencies.len() as f64,
        "p50_ms": stats::percentile_interpolated(&sorted, 0.5),
        "p90_ms": stats::percentile_interpolated(&sorted, 0.9),
        "p99_ms": stats::percentile_interpolated(&sorted, 0.99),
        "max_ms": sorted.last(),
        "peak_rss_kb": peak_kb,
        "rss_at_end_kb": rss_kb,
        "server_cpu_seconds": cpu.server,
        "client_cpu_seconds": cpu.client,
        "fallbacks": streamed.fallbacks,
        "poses_bytes": streamed.poses_received.map(|(bytes, _)| bytes),
        "poses_samples": streamed.poses_received.map(|(_, samples)| samples),
        "solves": stats["solves"],
        "skipped_solves": stats["skipped_solves"],
        "tracked_chi2": stats["chi2"],
        "max_update_ms": max_update_ms,
        // With a budget: provisional answers and the corrections that followed them.
        "latency": stats["latency"],
    });
    report["server_histograms"] = histograms;
    report["memory_at"] = json!(streamed.memory);
    if let Some(restarted) = restarted {
        report["restart"] = restarted;
    }
    for (k, v) in chi2.as_object().expect("an object") {
        report[k] = v.clone();
    }
    // The same once the session was idle and had polished (time from the last ack).
    report["idle_seconds_to_converge"] = json!(idle_seconds);
    for (k, v) in idle_chi2.as_object().expect("an object") {
        report[format!("idle_{k}")] = v.clone();
    }
    println!(
        "{}",
        serde_json::to_string_pretty(&report).expect("serialisable")
    );
    if let Some(out) = args.value("--json") {
        std::fs::write(out, report.to_string()).expect("writable --json");
    }
    if let Some(out) = args.value("--dump-latencies") {
        let lines: String = latencies.iter().map(|v| format!("{v:.6}\n")).collect();
        std::fs::write(out, lines).expect("writable --dump-latencies");
    }
}

/// Kills the server with SIGKILL and starts it again on its state directory: how long until
/// `session` answers with all `variables`, and the new server's peak memory then.
async fn restart_after_kill(s: TestServer, session: &str, fsync: &str, variables: Value) -> Value {
    let state_dir = s.state_dir.clone();
    let _ = s.kill();
    let started = std::time::Instant::now();
    let s = TestServer::start_at(&state_dir, &["--log", "warn", "--fsync", fsync], &[]);
    let c = common::server::client();
    let url = s.url(&format!("/v1/sessions/{session}"));
    loop {
        let (status, info) = get(&c, &url).await;
        if status == 200 && info["num_variables"] == variables {
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(1800),
            "the session did not come back: {status} {info}"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let seconds = started.elapsed().as_secs_f64();
    let report = json!({
        "restart_seconds": seconds,
        "peak_rss_kb": proc_status_kb(s.pid(), "VmHWM"),
        "state_dir_bytes": directory_bytes(&state_dir),
    });
    s.assert_no_panic();
    let _ = s.terminate(Duration::from_secs(10));
    report
}

/// Bytes of the files under `dir` (the journal and snapshots).
fn directory_bytes(dir: &std::path::Path) -> u64 {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    entries
        .flatten()
        .map(|e| match e.file_type() {
            Ok(t) if t.is_dir() => directory_bytes(&e.path()),
            _ => e.metadata().map_or(0, |m| m.len()),
        })
        .sum()
}
