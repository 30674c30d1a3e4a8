//! Scenario `fleet`: three `factord serve --fleet` instances on one shared state directory
//! (journal on), 100 robot sessions created through any instance (round robin), each robot a
//! zenoh peer connected to one instance, publishing one small numbered batch (a pose with its
//! odometry, sometimes a loop closure) at 10 Hz for 30 s; acks read on `out/acks` and
//! `out/errors`. A robot whose acks stall for 1 s resends from its covered frontier (repeats
//! are answered as duplicates), as a real client would; resends are counted.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde_json::{json, Value};

use crate::acks::{self, Tracker};
use crate::graph;
use crate::proc::{http_get, http_post, zenoh_get, zenoh_peer, Server};

/// Every instance's `info` (zenoh `factord/@fleet/*/info`).
async fn infos(z: &zenoh::Session) -> Vec<Value> {
    let replies = z
        .get("factord/@fleet/*/info")
        .target(zenoh::query::QueryTarget::All)
        .consolidation(zenoh::query::ConsolidationMode::None)
        .timeout(Duration::from_secs(2))
        .await
        .expect("query sent");
    let mut out = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result() {
            if let Ok(v) = serde_json::from_slice(&sample.payload().to_bytes()) {
                out.push(v);
            }
        }
    }
    out
}

/// Waits until every instance is settled and sees all `n`.
async fn settled(z: &zenoh::Session, n: usize) {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let all = infos(z).await;
        let ready = all.len() == n
            && all.iter().all(|i| {
                i["settled"] == true && i["live"].as_object().is_some_and(|l| l.len() == n)
            });
        if ready {
            return;
        }
        assert!(Instant::now() < deadline, "fleet did not settle: {all:?}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// One robot: publishes `batches` at `hz` from `start`, resending from the covered frontier
/// when its acks stall for a second; then waits (at most `drain`) for the rest. Returns resends.
async fn robot(
    z: Arc<zenoh::Session>,
    session: String,
    batches: Vec<(String, usize)>,
    tracker: acks::Shared,
    hz: f64,
    start: tokio::time::Instant,
    drain: Duration,
) -> u64 {
    let publisher = z
        .declare_publisher(format!("factord/{session}/in/batch"))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .expect("publisher");
    let mut tick = tokio::time::interval_at(start, Duration::from_secs_f64(1.0 / hz));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let (mut resent, mut stall_since, mut last_frontier) = (0u64, Instant::now(), 0u64);
    let resend = |frontier: u64, upto: usize, resent: &mut u64| -> Vec<String> {
        let out: Vec<String> = batches[frontier as usize..upto]
            .iter()
            .map(|b| b.0.clone())
            .collect();
        *resent += out.len() as u64;
        out
    };
    let n = batches.len();
    let mut next = 0usize;
    let end_by =
        Instant::now() + Duration::from_secs_f64(n as f64 / hz) + drain + Duration::from_secs(2);
    loop {
        tick.tick().await;
        let frontier = tracker.lock().expect("not poisoned").frontier();
        if frontier as usize >= n || Instant::now() > end_by {
            break;
        }
        if frontier > last_frontier || frontier as usize >= next {
            (last_frontier, stall_since) = (frontier, Instant::now());
        }
        if stall_since.elapsed() > Duration::from_secs(1) {
            for body in resend(frontier, next, &mut resent) {
                publisher.put(body).await.expect("published");
            }
            stall_since = Instant::now();
        }
        if next < n {
            tracker
                .lock()
                .expect("not poisoned")
                .sending(next as u64 + 1);
            publisher
                .put(batches[next].0.clone())
                .await
                .expect("published");
            next += 1;
        }
    }
    resent
}

/// `fleet [--robots 100] [--hz 10] [--seconds 30] [--instances 3] [--peers 100] [--fsync X]`
pub async fn run(args: &crate::args::Args) -> Vec<Value> {
    let robots: usize = args.parsed("--robots", 100);
    let hz: f64 = args.parsed("--hz", 10.0);
    let seconds: f64 = args.parsed("--seconds", 30.0);
    let n_inst: usize = args.parsed("--instances", 3);
    let peers: usize = args.parsed("--peers", robots).clamp(1, robots);
    let fsync = args.value("--fsync");
    let mut flags: Vec<&str> = Vec::new();
    if let Some(f) = fsync.as_deref() {
        flags.extend(["--fsync", f]);
    }
    let setup = Instant::now();
    let (fleet, dir) = Server::fleet(n_inst, &flags);
    let endpoints: Vec<&str> = fleet.iter().map(|s| s.zenoh.as_str()).collect();
    let watcher = zenoh_peer(&endpoints).await;
    settled(&watcher, n_inst).await;

    let c = reqwest::Client::new();
    let names: Vec<String> = (0..robots).map(|i| format!("r{i:03}")).collect();
    for (i, name) in names.iter().enumerate() {
        let url = fleet[i % n_inst].url("/v1/sessions");
        let body = json!({"session": name, "kind": "pose_graph_2d"});
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            let (status, answer) = http_post(&c, &url, &body).await;
            if status == 201 {
                break;
            }
            assert!(
                Instant::now() < deadline,
                "create {name}: {status} {answer}"
            );
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }
    // Robots' zenoh peers, each connected to one instance (round robin).
    let mut sessions = Vec::new();
    for p in 0..peers {
        sessions.push(Arc::new(zenoh_peer(&[endpoints[p % n_inst]]).await));
    }
    let per_robot = (hz * seconds).round() as usize;
    let mut trackers = Vec::new();
    let mut subs = Vec::new();
    let wake = Arc::new(tokio::sync::Notify::new());
    let mut all_batches = Vec::new();
    for (i, name) in names.iter().enumerate() {
        let z = &sessions[i % peers];
        let producer = format!("robot-{i}");
        let g = graph::manhattan(per_robot, 1000 + i as u64);
        all_batches.push(graph::per_pose(&g, &producer));
        let t = Tracker::new(&producer, per_robot);
        for topic in ["acks", "errors"] {
            let key = format!("factord/{name}/out/{topic}");
            subs.push(acks::subscribe(z, &key, t.clone(), wake.clone()).await);
        }
        // The session's keys are routed to its owner through this peer.
        zenoh_get(z, &format!("factord/{name}/estimate"), None)
            .await
            .expect("the session's queryable answers");
        trackers.push(t);
    }
    tokio::time::sleep(Duration::from_millis(1000)).await;
    // --sync: write back the dirty pages of the setup (session creation) before the run, so
    // the kernel's periodic writeback of them does not fall inside it.
    if args.has("--sync") {
        let _ = std::process::Command::new("sync").status();
    }
    let setup_seconds = setup.elapsed().as_secs_f64();
    let factors: usize = all_batches.iter().flatten().map(|b| b.1).sum();

    let start = tokio::time::Instant::now() + Duration::from_millis(200);
    let began = Instant::now();
    let cpu_before: Vec<f64> = fleet.iter().map(Server::cpu_seconds).collect();
    let own_cpu_before = crate::proc::cpu_seconds(std::process::id());
    let jitter = crate::jitter::Jitter::start();
    let mut tasks = Vec::new();
    for (i, batches) in all_batches.into_iter().enumerate() {
        // Robots' phases spread over one period.
        let offset = Duration::from_secs_f64(i as f64 / robots as f64 / hz);
        tasks.push(tokio::spawn(robot(
            sessions[i % peers].clone(),
            names[i].clone(),
            batches,
            trackers[i].clone(),
            hz,
            start + offset,
            Duration::from_secs(15),
        )));
    }
    let mut resent = 0;
    for t in tasks {
        resent += t.await.expect("robot task");
    }
    let wall = began.elapsed().as_secs_f64();
    let jitter = jitter.finish();
    let cpu: BTreeMap<String, f64> = fleet
        .iter()
        .zip(&cpu_before)
        .enumerate()
        .map(|(i, (s, b))| (format!("f{}", i + 1), s.cpu_seconds() - b))
        .collect();
    let own_cpu = crate::proc::cpu_seconds(std::process::id()) - own_cpu_before;
    let loadavg_at_end = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();

    // Client-side tally.
    let (mut lat, mut covered, mut lagged, mut errors, mut dups) = (Vec::new(), 0, 0, 0, 0);
    let (mut individually, mut cumulatively) = (0, 0);
    let mut first_errors = Vec::new();
    for t in &trackers {
        let t = t.lock().expect("not poisoned");
        lat.extend(t.latencies_ms());
        covered += t.covered;
        lagged += t.lagged_total();
        errors += t.errors.len();
        dups += t.duplicates;
        let (a, b) = t.split();
        individually += a;
        cumulatively += b;
        first_errors.extend(t.errors.iter().take(1).cloned());
    }
    let sent = (robots * per_robot) as u64;
    let (p50, p99, worst) = acks::summary(&mut lat);
    // Server-side: each session's counts through instance 0 (forwarded to the owner).
    let mut applied_ok = 0;
    for (i, name) in names.iter().enumerate() {
        let (_, info) = http_get(&c, &fleet[0].url(&format!("/v1/sessions/{name}"))).await;
        let (_, st) = http_get(
            &c,
            &fleet[0].url(&format!("/v1/sessions/{name}/producers/robot-{i}")),
        )
        .await;
        if info["sequence"].as_u64() == Some(per_robot as u64)
            && st["accepted_through"].as_u64() == Some(per_robot as u64)
        {
            applied_ok += 1;
        }
    }
    let mut owners: BTreeMap<String, usize> = BTreeMap::new();
    let mut owner_of: BTreeMap<String, String> = BTreeMap::new();
    for info in infos(&watcher).await {
        let instance = info["instance"].as_str().unwrap_or("?").to_string();
        for s in info["sessions"].as_array().into_iter().flatten() {
            let name = s.as_str().or(s["session"].as_str()).unwrap_or("?");
            owner_of.insert(name.to_string(), instance.clone());
            *owners.entry(instance.clone()).or_default() += 1;
        }
    }
    // Where the tail is: per owner instance, and the seconds of the run with most slow acks.
    let mut by_owner: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    let mut slow_by_second: BTreeMap<u64, u64> = BTreeMap::new();
    for (i, t) in trackers.iter().enumerate() {
        let t = t.lock().expect("not poisoned");
        let owner = owner_of
            .get(&names[i])
            .cloned()
            .unwrap_or_else(|| "?".into());
        by_owner.entry(owner).or_default().extend(t.latencies_ms());
        for (sent_at, ms) in t.timed_latencies_ms() {
            if ms > 20.0 {
                let second = sent_at.saturating_duration_since(began).as_secs();
                *slow_by_second.entry(second).or_default() += 1;
            }
        }
    }
    let owner_tail: BTreeMap<String, Value> = by_owner
        .into_iter()
        .map(|(k, mut v)| {
            let (p50, p99, worst) = acks::summary(&mut v);
            (
                k,
                json!({"p50_ms": p50, "p99_ms": p99, "worst_ms": worst, "acks": v.len()}),
            )
        })
        .collect();
    let mut slowest: Vec<(u64, u64)> = slow_by_second.into_iter().collect();
    slowest.sort_by_key(|(s, n)| (std::cmp::Reverse(*n), *s));
    slowest.truncate(8);
    let slow_acks: u64 = lat.iter().filter(|&&v| v > 20.0).count() as u64;
    let mut server_metrics: BTreeMap<String, Vec<String>> = BTreeMap::new();
    for (i, s) in fleet.iter().enumerate() {
        let lines = crate::proc::metrics(
            &c,
            s,
            &[
                "fsync_seconds_sum",
                "fsync_seconds_count",
                "solve_duration_seconds_sum",
                "solve_duration_seconds_count",
                "batches_accepted_total",
                // Group commit (journal::group_commit): fdatasyncs and the records they covered.
                "group_fsyncs_total",
                "group_fsynced_records_total",
            ],
        )
        .await;
        let buckets = crate::proc::metric_buckets(
            &c,
            s,
            "factord_journal_fsync_seconds",
            &["0.01", "0.025", "+Inf"],
        )
        .await;
        server_metrics.insert(
            format!("f{}", i + 1),
            lines.into_iter().chain(buckets).collect(),
        );
    }
    let rss: BTreeMap<String, f64> = fleet
        .iter()
        .enumerate()
        .map(|(i, s)| (format!("f{}", i + 1), s.peak_rss_kib() as f64 / 1024.0))
        .collect();
    let warnings: Vec<String> = fleet.iter().flat_map(|s| s.warnings()).take(5).collect();
    for z in sessions {
        if let Ok(z) = Arc::try_unwrap(z) {
            let _ = z.close().await;
        }
    }
    drop(subs);
    let _ = watcher.close().await;
    drop(fleet);
    let _ = std::fs::remove_dir_all(&dir);
    vec![json!({
        "scenario": "fleet",
        "instances": n_inst,
        "robots": robots,
        "zenoh_peers": peers,
        "hz": hz,
        "seconds": seconds,
        "fsync": fsync.unwrap_or_else(|| "always (default)".into()),
        "batches": sent,
        "factors": factors,
        "setup_seconds": setup_seconds,
        "synced_before_run": args.has("--sync"),
        "wall_seconds": wall,
        "covered": covered,
        "lost": sent - covered.min(sent),
        "acked_individually": individually,
        "covered_only_cumulatively": cumulatively,
        "resent": resent,
        "duplicates": dups,
        "lagged_markers": lagged,
        "error_events": errors,
        "first_errors": first_errors.into_iter().take(3).collect::<Vec<_>>(),
        "sessions_applied_exactly": applied_ok,
        "sessions_per_instance": owners,
        "ack_p50_ms": p50,
        "ack_p99_ms": p99,
        "ack_worst_ms": worst,
        "target_p99_ms": 20,
        "target_met": p99 < 20.0 && covered == sent,
        "peak_rss_mib": rss,
        "acks_over_20ms": slow_acks,
        "tail_by_owner": owner_tail,
        "seconds_with_most_acks_over_20ms": slowest,
        "cpu_seconds_during_run": cpu,
        "bench_client_cpu_seconds": own_cpu,
        "loadavg_at_end": loadavg_at_end.trim(),
        "machine_wakeup_jitter": jitter,
        "server_metrics": server_metrics,
        "server_warnings": warnings,
    })]
}
