//! Streams a 2D g2o pose graph into a session one pose at a time (each pose with every edge
//! whose later end is that pose; no value for a pose with an odometry edge, so the service
//! predicts it) and measures, per update, the time until the estimate reflects it: the same
//! protocol as `isam2_stream.py`. Runs the service in-process through its command API (no
//! transport), so this measures the session engine.
//!
//! `cargo bench --bench incremental_stream -- <file.g2o> [--json out.json] [--limit N]
//! [--dump-latencies out.txt] [--dump-reports out.jsonl] [--accuracy-every N]` (2D or 3D g2o;
//! the latency dump has one latency in ms per line, in stream order; the report dump one engine
//! `UpdateReport` per incremental update). Every 1000 updates, that window's p50, p99 and worst go to stderr.
//!
//! `--accuracy-every N` also takes the answered estimate right after every N-th update (and
//! the last) and scores it afterwards: its true chi2 on the graph streamed so far, relative to
//! that graph's batch optimum (`accuracy`: p50 / p99 / max of the excess). It is how far the
//! answers a robot gets during the stream are from the exact ones, which the end-of-stream
//! figures do not show.

#[path = "../../tests/common/mod.rs"]
mod common;

#[path = "../args.rs"]
mod args;
#[path = "../stats.rs"]
mod stats;

use std::collections::HashSet;
use std::time::Instant;

use common::server::g2o_batches;

use factord::api::wire::{Batch, CreateSession, Estimate, SessionEvent};
use factord::api::{ApplyBatch, DeleteSession, GetStats, Optimize, Optimizing};
use factord::service::{Caller, Command, Limits, Recording, Reply, Service};
use factord::solver::{optimize, SolverOptions};

/// Updates per progress line on stderr (that window's p50, p99 and worst).
const PROGRESS_EVERY: usize = 1000;

fn main() {
    let args = args::Args::from_env();
    let path = args.first("usage: incremental_stream <file.g2o> [--json out] [--limit N]");
    let limit: usize = args.parsed("--limit", usize::MAX);
    let accuracy_every: usize = args.parsed("--accuracy-every", 0);
    let text = std::fs::read_to_string(&path).expect("readable graph");

    // The streaming order shared with the tests: pose k with the edges whose later end is k.
    let mut batches: Vec<Batch> = g2o_batches(&text)
        .into_iter()
        .map(|b| serde_json::from_value(b).expect("g2o_batches makes valid batches"))
        .collect();
    batches.truncate(limit);
    let kept: HashSet<u64> = batches
        .iter()
        .flat_map(|b| b.variables.iter().map(|v| v.key))
        .collect();
    // The keys each batch brings, in stream order (the graph streamed up to an update).
    let answered_keys: Vec<Vec<u64>> = batches
        .iter()
        .map(|b| b.variables.iter().map(|v| v.key).collect())
        .collect();

    let kind = match batches.first().map(|b| b.variables[0].kind.as_str()) {
        Some("se3") => "pose_graph_3d",
        _ => "pose_graph_2d",
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .unwrap();
    let report = runtime.block_on(async {
        let service = Service::new(Limits::default());
        service
            .execute(
                &Caller::Trusted,
                // From JSON, as a client sends it: the fields it leaves out take their defaults.
                Command::CreateSession(
                    serde_json::from_value::<CreateSession>(serde_json::json!({
                        "session": "bench",
                        "kind": kind,
                    }))
                    .expect("a valid create request"),
                ),
                Recording::History,
            )
            .await
            .expect("session");
        // Where solve time goes: every Summary the session streams.
        let mut events = service.session("bench").expect("created").stream();
        let phases = tokio::spawn(async move {
            let mut totals = serde_json::Map::new();
            let mut add = |k: &str, v: f64| {
                let e = totals.entry(k.to_string()).or_insert(0.0.into());
                *e = (e.as_f64().unwrap() + v).into();
            };
            let mut reports = Vec::new();
            while let Some(event) = events.next().await {
                if let SessionEvent::Summary { summary, .. } = &*event {
                    if let Some(report) = &summary.used.incremental {
                        reports.push(serde_json::to_string(report).expect("serialisable"));
                    }
                    let t = &summary.timings;
                    add("solve", summary.solve_seconds);
                    match summary.used.region_variables {
                        Some(n) => {
                            add("region_solves", 1.0);
                            add("region_solve_seconds", summary.solve_seconds);
                            add("region_variables", n as f64);
                        }
                        None => {
                            add("full_solves", 1.0);
                            add("full_solve_seconds", summary.solve_seconds);
                        }
                    }
                    add("iterations", summary.iterations as f64);
                    add("preprocess", t.preprocess_seconds);
                    add("linearize", t.linearize_seconds);
                    add("factorize", t.factorize_seconds);
                    add("linear_solve", t.linear_solve_seconds);
                    add("evaluate", t.evaluate_seconds);
                }
            }
            (totals, reports)
        });
        let mut latencies = Vec::with_capacity(batches.len());
        let mut answers: Vec<(usize, Estimate)> = Vec::new();
        let updates = batches.len();
        let start = Instant::now();
        for batch in batches {
            let t = Instant::now();
            let reply = service
                .execute(
                    &Caller::Trusted,
                    Command::ApplyBatch(ApplyBatch {
                        session: "bench".into(),
                        batch,
                        wait: true,
                    }),
                    Recording::History,
                )
                .await
                .expect("batch accepted");
            latencies.push(t.elapsed().as_secs_f64() * 1e3);
            if latencies.len() % PROGRESS_EVERY == 0 {
                // Long streams (100k poses) report as they go: a window survives a stopped run.
                let mut window = latencies[latencies.len() - PROGRESS_EVERY..].to_vec();
                window.sort_by(f64::total_cmp);
                eprintln!(
                    "updates {}: p50 {:.3} ms, p99 {:.3} ms, worst {:.3} ms",
                    latencies.len(),
                    stats::percentile(&window, 0.5),
                    stats::percentile(&window, 0.99),
                    window[PROGRESS_EVERY - 1]
                );
            }
            if let Reply::Accepted(a) = reply {
                assert_eq!(a.solved, Some(true), "estimate reflects the update");
            }
            let done = latencies.len();
            if accuracy_every > 0 && (done % accuracy_every == 0 || done == updates) {
                // Taken at once, before an idle session could polish it.
                let Reply::Estimate(estimate) = service
                    .execute(
                        &Caller::Trusted,
                        Command::get_estimate("bench".into(), Default::default()),
                        Recording::History,
                    )
                    .await
                    .expect("estimate")
                else {
                    unreachable!()
                };
                answers.push((done, estimate));
            }
        }
        let total = start.elapsed().as_secs_f64();
        let Reply::Stats(stats) = service
            .execute(
                &Caller::Trusted,
                Command::GetStats(GetStats {
                    session: "bench".into(),
                }),
                Recording::History,
            )
            .await
            .unwrap()
        else {
            unreachable!()
        };
        // The true chi2 of the streamed estimate (the initial chi2 of a full solve from it), and
        // where a final full solve takes it.
        let Reply::Optimizing(Optimizing {
            stats: Some(after), ..
        }) = service
            .execute(
                &Caller::Trusted,
                Command::Optimize(Optimize {
                    session: "bench".into(),
                    wait: true,
                    after: Default::default(),
                }),
                Recording::History,
            )
            .await
            .unwrap()
        else {
            unreachable!()
        };
        let check = after.last_summary.expect("a full solve ran");
        let check = (check.initial_chi2, check.final_chi2);
        service
            .execute(
                &Caller::Trusted,
                Command::DeleteSession(DeleteSession {
                    session: "bench".into(),
                }),
                Recording::History,
            )
            .await
            .expect("deleted");
        drop(service);
        let (phases, reports) = phases.await.expect("phase totals");
        if let Some(out) = args.value("--dump-reports") {
            let lines: String = reports.iter().map(|r| format!("{r}\n")).collect();
            std::fs::write(out, lines).expect("writable --dump-reports");
        }
        (latencies, total, stats, phases, check, answers)
    });
    let (mut latencies, total, stats, phases, check, answers) = report;

    // The batch optimum of the same (possibly truncated) graph, for the chi2 comparison.
    let batch = batch_optimum(&text, &path, &kept).final_chi2;
    let accuracy = answer_accuracy(&text, &path, &answered_keys, &answers);

    if let Some(out) = args.value("--dump-latencies") {
        let lines: String = latencies.iter().map(|ms| format!("{ms}\n")).collect();
        std::fs::write(out, lines).expect("writable --dump-latencies");
    }
    let mean = latencies.iter().sum::<f64>() / latencies.len() as f64;
    latencies.sort_by(f64::total_cmp);
    let final_chi2 = stats.chi2.unwrap_or(f64::NAN);
    let json = serde_json::json!({
        "dataset": path,
        "steps": latencies.len(),
        "total_seconds": total,
        "mean_ms": mean,
        "p50_ms": stats::percentile(&latencies, 0.5),
        "p90_ms": stats::percentile(&latencies, 0.9),
        "p99_ms": stats::percentile(&latencies, 0.99),
        "max_ms": latencies.last(),
        "solves": stats.solves,
        "skipped_solves": stats.skipped_solves,
        "tracked_chi2": final_chi2,
        "batch_chi2": batch,
        "chi2_excess": check.0 / batch - 1.0,
        "streamed_estimate_chi2": check.0,
        "chi2_after_a_final_full_solve": check.1,
        "solve_phase_seconds": phases,
        "accuracy": accuracy,
    });
    println!("{}", serde_json::to_string_pretty(&json).unwrap());
    if let Some(out) = args.value("--json") {
        std::fs::write(out, json.to_string()).expect("writable --json");
    }
}

/// The lines of `text` among `kept` vertices: the graph as streamed up to some update.
fn prefix_text(text: &str, kept: &HashSet<u64>) -> String {
    text.lines()
        .filter(|l| {
            let t: Vec<&str> = l.split_whitespace().collect();
            match t.first() {
                Some(tag) if tag.starts_with("VERTEX") => kept.contains(&t[1].parse().unwrap()),
                Some(tag) if tag.starts_with("EDGE") => {
                    kept.contains(&t[1].parse().unwrap()) && kept.contains(&t[2].parse().unwrap())
                }
                _ => false,
            }
        })
        .map(|l| format!("{l}\n"))
        .collect()
}

fn prefix_graph(text: &str, path: &str, kept: &HashSet<u64>) -> factord::io::PoseGraph {
    factord::io::parse_text(&prefix_text(text, kept), std::path::Path::new(path), None)
        .expect("graph")
}

fn batch_optimum(text: &str, path: &str, kept: &HashSet<u64>) -> factord::solver::Summary {
    let mut graph = prefix_graph(text, path, kept);
    optimize(&mut graph.problem, &SolverOptions::default(), &mut |_| {
        std::ops::ControlFlow::Continue(())
    })
    .expect("batch solve")
}

/// Each answer's true chi2 on the graph streamed up to it, relative to that graph's batch
/// optimum: p50 / p99 / max over the answers taken (`--accuracy-every`).
fn answer_accuracy(
    text: &str,
    path: &str,
    answered_keys: &[Vec<u64>],
    answers: &[(usize, Estimate)],
) -> serde_json::Value {
    if answers.is_empty() {
        return serde_json::Value::Null;
    }
    let mut excess = Vec::with_capacity(answers.len());
    for (updates, estimate) in answers {
        let kept: HashSet<u64> = answered_keys[..*updates]
            .iter()
            .flatten()
            .copied()
            .collect();
        let optimum = batch_optimum(text, path, &kept).final_chi2;
        let mut answered = prefix_graph(text, path, &kept).problem;
        for v in &estimate.variables {
            let idx = answered.values.index_of(v.key).expect("a streamed key");
            let set = match v.value.as_slice() {
                &[x, y, theta] => answered
                    .values
                    .set(idx, &factord::geometry::Se2::new(x, y, theta)),
                &[x, y, z, qx, qy, qz, qw] => answered.values.set(
                    idx,
                    &factord::geometry::Se3::new(
                        nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
                            qw, qx, qy, qz,
                        )),
                        nalgebra::Vector3::new(x, y, z),
                    ),
                ),
                other => panic!("a pose value of {} numbers", other.len()),
            };
            assert!(set, "the estimate's value fits its variable");
        }
        excess.push(answered.chi2() / optimum - 1.0);
    }
    let mut sorted = excess.clone();
    sorted.sort_by(f64::total_cmp);
    serde_json::json!({
        "answers": excess.len(),
        "excess_p50": stats::percentile(&sorted, 0.5),
        "excess_p99": stats::percentile(&sorted, 0.99),
        "excess_max": sorted.last(),
        "excess_mean": excess.iter().sum::<f64>() / excess.len() as f64,
    })
}
