//! Giant batch jobs against the real server: a job stops near its time limit even when one
//! factorisation of its graph takes most of a minute, and other sessions are served while giant
//! jobs run (the pool keeps a worker for them, and jobs yield at the solver's checkpoints).

use crate::common;

use std::time::{Duration, Instant};

use common::server::{create, post, post_job_within, start_with_limits};
use serde_json::json;

/// Query parameters no tolerance can stop: the job runs until its time limit.
const ENDLESS: &str =
    "max_iterations=100000&function_tolerance=0&gradient_tolerance=0&parameter_tolerance=0";

/// 60k poses in a 40 m building: one factorisation takes ~48 s and 2.4 GB on the machine this
/// was measured on; before fine-grained budgets the job answered after ~54 s.
#[tokio::test(flavor = "multi_thread")]
async fn a_giant_job_stops_within_twice_its_time_limit() {
    let limit = Duration::from_millis(3000);
    let s = start_with_limits(&json!({"max_solve_ms": limit.as_millis() as u64}));
    let graph = common::synthetic_building(60_000, 1, 40, 2);
    let (status, v, wall) = post_job_within(&s, ENDLESS, graph, 2 * limit).await;
    eprintln!(
        "60k-pose building job, max_solve_ms {}: answered in {:.2} s after {} iterations ({})",
        limit.as_millis(),
        wall.as_secs_f64(),
        v["summary"]["iterations"],
        v["summary"]["termination"]["message"]
    );
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["summary"]["termination"]["reason"], "interrupted", "{v}");
    assert!(wall < 2 * limit, "{wall:?}");
    assert_eq!(
        v["estimate"]["variables"].as_array().map(Vec::len),
        Some(60_000)
    );
    s.assert_no_panic();
}

/// Three jobs whose iterations take seconds each, on two workers; a trivial batch of another
/// session, with `wait=true`, is answered within 0.5 s every time.
#[tokio::test(flavor = "multi_thread")]
async fn another_sessions_batch_is_answered_quickly_during_three_giant_jobs() {
    let s = start_with_limits(&json!({"workers": 2, "max_jobs": 4, "max_solve_ms": 60_000}));
    let graph = common::synthetic_building(30_000, 2, 30, 2);
    let c = common::server::client();
    let mut jobs = Vec::new();
    for _ in 0..3 {
        let (c, url, body) = (
            c.clone(),
            s.url(&format!("/v1/jobs?{ENDLESS}")),
            graph.clone(),
        );
        jobs.push(tokio::spawn(async move {
            c.post(url).body(body).send().await.map(|r| r.status())
        }));
    }
    // Long enough for the jobs to be parsed and deep in their first factorisations.
    tokio::time::sleep(Duration::from_secs(4)).await;
    create(
        &c,
        &s,
        &json!({"session": "small", "kind": "pose_graph_2d"}),
    )
    .await;
    let url = s.url("/v1/sessions/small/batches?wait=true");
    let mut latencies = Vec::new();
    for k in 0..5u64 {
        // A guess off the measurement, so that every batch needs a solve (an odometry-predicted
        // pose would be answered without one).
        let variable = json!({"key": k, "kind": "se2", "value": [k as f64 + 0.3, 0.2, 0.05]});
        let factors = if k == 0 {
            json!([])
        } else {
            json!([{"type": "between_se2", "keys": [k - 1, k], "measurement": [1, 0, 0.1],
                    "information": [100, 0, 0, 100, 0, 400]}])
        };
        let batch = json!({"variables": [variable], "factors": factors});
        let start = Instant::now();
        let (status, v) = post(&c, &url, &batch).await;
        latencies.push(start.elapsed());
        assert_eq!(status, 200, "{v}");
        assert_eq!(v["solved"], true, "the batch was solved: {v}");
        tokio::time::sleep(Duration::from_millis(300)).await;
    }
    let worst = latencies.iter().max().copied().unwrap_or_default();
    eprintln!("batch latencies during 3 giant jobs: {latencies:?}");
    assert!(
        worst < Duration::from_millis(500),
        "a batch waited {worst:?}: {latencies:?}"
    );
    for job in &jobs {
        assert!(!job.is_finished(), "the giant jobs were still running");
    }
    s.assert_no_panic();
}
