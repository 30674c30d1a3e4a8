//! The robot link measured as users see it, end to end through real `factord serve` release
//! processes (journal on, free loopback ports, temporary state directories) and real zenoh
//! peers as robots (issue 17's acceptance):
//!
//! - `stream`: `input_M3500_g2o` and a generated 50k-pose Manhattan graph published pose by
//!   pose at full rate (Block); every batch covered by an ack, applied once; rates, ack
//!   latency (send → covering ack) p50/p99/worst, lagged markers, server peak RSS.
//! - `ingest`: 1000-factor batches with `--fsync interval`: factors/s (target ≥ 200 000) and
//!   the same payloads through a bare zenoh echo peer as the machine's reference.
//! - `fleet`: 3 `--fleet` instances on one state directory, 100 robots at 10 Hz for 30 s: ack
//!   latency p50/p99/worst (target p99 < 20 ms), acks lost (must be 0), peak RSS per instance.
//!
//! `cargo bench --bench link -- stream|ingest|fleet [options]` (see each scenario's file).
//! Prints one JSON line per measurement and a table; `--json FILE` appends the lines to FILE.

#[path = "../args.rs"]
mod args;

mod acks;
mod fleet;
mod graph;
mod ingest;
mod jitter;
mod proc;
mod stream;

use serde_json::{json, Value};

/// The machine and build the numbers come from.
fn machine() -> Value {
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .unwrap_or_default()
        .lines()
        .find(|l| l.starts_with("model name"))
        .and_then(|l| l.split(':').nth(1))
        .map(|s| s.trim().to_string());
    let commit = std::process::Command::new("git")
        .args(["rev-parse", "--short", "HEAD"])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .ok()
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string());
    let date = std::process::Command::new("date")
        .args(["-u", "+%Y-%m-%dT%H:%M:%SZ"])
        .output()
        .ok()
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string());
    json!({"cores": cores, "cpu": cpu, "loadavg_at_start": load.trim(), "commit": commit,
           "date": date})
}

fn table(rows: &[Value]) {
    let cols = [
        ("scenario", "scenario"),
        ("graph/system", "graph"),
        ("batches", "batches"),
        ("factors", "factors"),
        ("lost", "lost"),
        ("indiv/cumul", ""),
        ("lagged", "lagged_markers"),
        ("resent", "resent"),
        ("total s", "total_seconds"),
        ("batch/s", "batches_per_s"),
        ("factor/s", "factors_per_s"),
        ("p50 ms", "ack_p50_ms"),
        ("p99 ms", "ack_p99_ms"),
        ("worst ms", "ack_worst_ms"),
        ("peak RSS MiB", "server_peak_rss_mib"),
    ];
    let cell = |r: &Value, key: &str| -> String {
        let v = match key {
            "graph" => r
                .get("graph")
                .or(r.get("system"))
                .cloned()
                .unwrap_or(Value::Null),
            "" => json!(format!(
                "{}/{}",
                r["acked_individually"], r["covered_only_cumulatively"]
            )),
            "total_seconds" => r
                .get("total_seconds")
                .or(r.get("wall_seconds"))
                .cloned()
                .unwrap_or(Value::Null),
            "server_peak_rss_mib" => r
                .get("server_peak_rss_mib")
                .or(r.get("peak_rss_mib"))
                .or(r.get("echo_peak_rss_mib"))
                .cloned()
                .unwrap_or(Value::Null),
            k => r.get(k).cloned().unwrap_or(Value::Null),
        };
        match v {
            Value::Number(n) if n.is_f64() => {
                let f = n.as_f64().unwrap_or(f64::NAN);
                if f.abs() >= 100.0 {
                    format!("{f:.0}")
                } else {
                    format!("{f:.2}")
                }
            }
            Value::String(s) => s,
            Value::Null => "-".into(),
            Value::Object(m) => m
                .iter()
                .map(|(k, v)| format!("{k}:{:.0}", v.as_f64().unwrap_or(f64::NAN)))
                .collect::<Vec<_>>()
                .join(" "),
            other => other.to_string(),
        }
    };
    let header: Vec<&str> = cols.iter().map(|c| c.0).collect();
    println!("| {} |", header.join(" | "));
    println!("|{}", "---|".repeat(cols.len()));
    for r in rows {
        let cells: Vec<String> = cols.iter().map(|c| cell(r, c.1)).collect();
        println!("| {} |", cells.join(" | "));
    }
}

fn main() {
    let args = args::Args::from_env();
    let usage = "usage: cargo bench --bench link -- stream|ingest|fleet [options] [--json FILE]";
    let scenario = args.first(usage);
    if scenario == "__echo" {
        let listen = args
            .value("__echo")
            .unwrap_or_else(|| panic!("__echo <endpoint>"));
        ingest::echo_main(&listen);
        return;
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("tokio runtime");
    let machine = machine();
    let rows = runtime.block_on(async {
        match scenario.as_str() {
            "stream" => stream::run(&args).await,
            "ingest" => ingest::run(&args).await,
            "fleet" => fleet::run(&args).await,
            _ => panic!("{usage}"),
        }
    });
    let mut lines = String::new();
    for r in &rows {
        let mut r = r.clone();
        r["machine"] = machine.clone();
        let line = r.to_string();
        println!("{line}");
        lines.push_str(&line);
        lines.push('\n');
    }
    println!();
    table(&rows);
    if let Some(out) = args.value("--json") {
        use std::io::Write as _;
        let mut f = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(out)
            .expect("writable --json");
        f.write_all(lines.as_bytes()).expect("written");
    }
}
