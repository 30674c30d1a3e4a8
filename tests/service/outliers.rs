//! Wrong loop closures in a streaming session (issue 54 item 3): a session created with
//! `"outliers": "auto"` (or factors marked `"outlier": "auto"`) holds every loop closure out of
//! the estimate until the gate finds it consistent, and consolidates the decisions by graduated
//! non-convexity once it rests. Streamed over HTTP and zenoh, M3500 with random wrong closures
//! ends at the clean optimum with exactly the wrong ones rejected; a kill -9 and restart
//! decides them again from the journal to the same answer.

use crate::common;

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use common::m3500::{clean_optimum, m3500, worst_error};
use common::server::{client, create, g2o_batches, get, post, zenoh_get, TestServer};
use common::wrong_closures::add_random_wrong_closures;
use serde_json::{json, Value};

/// The wrong closures `add_random_wrong_closures` appended at `lines`: (from, to, bits of the
/// measured x), which no right closure shares.
fn wrong_pairs(text: &str, lines: &BTreeSet<usize>) -> BTreeSet<(u64, u64, u64)> {
    text.lines()
        .enumerate()
        .filter(|(i, _)| lines.contains(&(i + 1)))
        .map(|(_, l)| {
            let f: Vec<&str> = l.split_whitespace().collect();
            let x: f64 = f[3].parse().unwrap();
            (f[1].parse().unwrap(), f[2].parse().unwrap(), x.to_bits())
        })
        .collect()
}

/// The factor ids a batch's acknowledgement gave its wrong closures.
fn wrong_ids(batch: &Value, ack: &Value, wrong: &BTreeSet<(u64, u64, u64)>) -> Vec<u64> {
    let factors = batch["factors"].as_array().unwrap();
    let ids = ack["factor_ids"].as_array().unwrap();
    factors
        .iter()
        .zip(ids)
        .filter(|(f, _)| {
            let (k, x) = (&f["keys"], f["measurement"][0].as_f64().unwrap());
            wrong.contains(&(k[0].as_u64().unwrap(), k[1].as_u64().unwrap(), x.to_bits()))
        })
        .map(|(_, id)| id.as_u64().unwrap())
        .collect()
}

fn ids_of(list: &Value) -> BTreeSet<u64> {
    list.as_array()
        .unwrap()
        .iter()
        .map(|c| c["factor_id"].as_u64().unwrap())
        .collect()
}

/// Waits until the session has consolidated `at_least` times (its gate decisions, once idle).
async fn consolidated(c: &reqwest::Client, url: &str, at_least: u64) -> Value {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let (status, report) = get(c, url).await;
        assert_eq!(status, 200, "{report}");
        if report["consolidations"].as_u64().unwrap() >= at_least && report["pending"] == json!([])
        {
            return report;
        }
        assert!(Instant::now() < deadline, "no consolidation: {report}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn wrong_closures_streamed_over_http_are_rejected_and_the_map_is_the_clean_optimum() {
    let Some(clean) = m3500(3500) else {
        return common::skip_or_fail("input_M3500_g2o.g2o is not in the data directory")
            .unwrap_or_default();
    };
    let (text, closures, lines) = add_random_wrong_closures(&clean, 0.2, 54);
    let wrong = wrong_pairs(&text, &lines);
    assert!(
        wrong.len() > 300,
        "{} wrong of {closures} closures",
        wrong.len()
    );
    let (clean_chi2, optimum) = clean_optimum(&clean);
    let s = TestServer::start(&[]);
    let c = client();
    create(
        &c,
        &s,
        &json!({"session": "m", "kind": "pose_graph_2d", "outliers": "auto"}),
    )
    .await;
    let mut wrong_ids_sent = BTreeSet::new();
    let start = Instant::now();
    for batch in g2o_batches(&text) {
        let (status, ack) = post(&c, &s.url("/v1/sessions/m/batches"), &batch).await;
        assert_eq!(status, 200, "{ack}");
        wrong_ids_sent.extend(wrong_ids(&batch, &ack, &wrong));
    }
    let streamed = start.elapsed();
    assert_eq!(wrong_ids_sent.len(), wrong.len());
    let (_, v) = post(&c, &s.url("/v1/sessions/m/optimize?wait=true"), &json!({})).await;
    let (_, gated) = get(&c, &s.url("/v1/sessions/m/outliers")).await;
    let gated_out = ids_of(&gated["rejected"]);
    let caught = gated_out.intersection(&wrong_ids_sent).count();
    println!(
        "streamed {} batches in {streamed:?}; the gate alone: {} rejected, {caught} of {} wrong (chi2 {})",
        3500,
        gated_out.len(),
        wrong_ids_sent.len(),
        v["stats"]["chi2"]
    );
    // The gate alone, before consolidation: most of the wrong ones out already.
    assert!(
        caught as f64 >= 0.9 * wrong_ids_sent.len() as f64,
        "{gated}"
    );
    let report = consolidated(&c, &s.url("/v1/sessions/m/outliers"), 1).await;
    assert_eq!(
        ids_of(&report["rejected"]),
        wrong_ids_sent,
        "exactly the wrong ones rejected"
    );
    assert_eq!(report["policy"], "auto");
    assert_eq!(
        report["accepted"].as_u64().unwrap() as usize,
        closures,
        "every right closure in the map"
    );
    let (_, summary) = get(&c, &s.url("/v1/sessions/m/summary")).await;
    let chi2 = summary["final_chi2"].as_f64().unwrap();
    let (_, estimate) = get(&c, &s.url("/v1/sessions/m/estimate")).await;
    let worst = worst_error(&estimate, &optimum);
    println!("consolidated: chi2 {chi2} (clean {clean_chi2}), worst position error {worst:.2e} m");
    assert!(
        (chi2 - clean_chi2).abs() <= 1e-5 * clean_chi2,
        "{chi2} vs {clean_chi2}"
    );
    assert!(worst < 1e-3, "{worst} m from the clean optimum");
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn marked_closures_over_zenoh_are_decided_and_the_decisions_are_events() {
    let Some(clean) = m3500(600) else {
        return common::skip_or_fail("input_M3500_g2o.g2o is not in the data directory")
            .unwrap_or_default();
    };
    let (text, _, lines) = add_random_wrong_closures(&clean, 0.2, 7);
    let wrong = wrong_pairs(&text, &lines);
    let (_, optimum) = clean_optimum(&clean);
    let s = TestServer::start(&[]);
    let z = common::server::zenoh_peer(&s.zenoh).await;
    let rpc = |command: Value| {
        let z = z.clone();
        async move { zenoh_get(&z, "factord/rpc", Some(&command)).await.unwrap() }
    };
    // No session policy: only the factors marked as possibly wrong are candidates.
    rpc(json!({"op": "create_session", "session": "zo", "kind": "pose_graph_2d"})).await;
    let (_sub, events) = common::server::json_samples(&z, "factord/zo/out/outliers").await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let mut sent = BTreeSet::new();
    for mut batch in g2o_batches(&text) {
        for f in batch["factors"].as_array_mut().unwrap() {
            let k = &f["keys"];
            if k[0].as_u64().unwrap().abs_diff(k[1].as_u64().unwrap()) != 1 {
                f["outlier"] = json!("auto");
            }
        }
        let ack = rpc(json!({"op": "apply_batch", "session": "zo", "batch": batch.clone()})).await;
        sent.extend(wrong_ids(&batch, &ack, &wrong));
    }
    // The events say which closures left the estimate and which entered (a consolidation only
    // tells what it changed).
    let deadline = Instant::now() + Duration::from_secs(60);
    let mut rejected = BTreeSet::new();
    while rejected != sent {
        let left = deadline.saturating_duration_since(Instant::now());
        let event = events.recv_timeout(left).expect("outliers events");
        assert_eq!(event["type"], "outliers", "{event}");
        assert_eq!(event["session"], "zo");
        rejected.extend(ids_of(&event["rejected"]));
        for id in ids_of(&event["accepted"]) {
            rejected.remove(&id);
        }
    }
    let report = loop {
        let report = rpc(json!({"op": "list_outliers", "session": "zo"})).await;
        if report["consolidations"].as_u64().unwrap() >= 1 && report["pending"] == json!([]) {
            break report;
        }
        assert!(Instant::now() < deadline, "no consolidation: {report}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    assert_eq!(ids_of(&report["rejected"]), sent, "{report}");
    assert_eq!(report["policy"], "off");
    let estimate = rpc(json!({"op": "get_estimate", "session": "zo"})).await;
    let worst = worst_error(&estimate, &optimum);
    assert!(worst < 1e-3, "{worst} m from the clean optimum");
}

#[tokio::test(flavor = "multi_thread")]
async fn decisions_are_taken_again_after_kill_9_from_the_journal() {
    let Some(clean) = m3500(1000) else {
        return common::skip_or_fail("input_M3500_g2o.g2o is not in the data directory")
            .unwrap_or_default();
    };
    let (text, _, lines) = add_random_wrong_closures(&clean, 0.2, 11);
    let wrong = wrong_pairs(&text, &lines);
    let (_, optimum) = clean_optimum(&clean);
    let dir = common::temp_dir("outliers-journal");
    let config = dir.with_extension("json");
    std::fs::write(
        &config,
        json!({"journal": {"snapshot_every": 200}}).to_string(),
    )
    .unwrap();
    let config = config.display().to_string();
    let extra = ["--config", config.as_str()];
    let s = TestServer::start_at(&dir, &extra, &[]);
    let c = client();
    create(
        &c,
        &s,
        &json!({"session": "j", "kind": "pose_graph_2d", "outliers": "auto"}),
    )
    .await;
    let mut sent = BTreeSet::new();
    for batch in g2o_batches(&text) {
        let (status, ack) = post(&c, &s.url("/v1/sessions/j/batches"), &batch).await;
        assert_eq!(status, 200, "{ack}");
        sent.extend(wrong_ids(&batch, &ack, &wrong));
    }
    let before = consolidated(&c, &s.url("/v1/sessions/j/outliers"), 1).await;
    assert_eq!(ids_of(&before["rejected"]), sent);
    s.kill();
    let s = TestServer::start_at(&dir, &extra, &[]);
    common::server::recovered(&c, &s, "j", Instant::now()).await;
    let after = consolidated(&c, &s.url("/v1/sessions/j/outliers"), 1).await;
    assert_eq!(
        ids_of(&after["rejected"]),
        sent,
        "the same closures rejected after recovery"
    );
    assert_eq!(after["accepted"], before["accepted"]);
    let (_, estimate) = get(&c, &s.url("/v1/sessions/j/estimate")).await;
    let worst = worst_error(&estimate, &optimum);
    assert!(
        worst < 1e-3,
        "{worst} m from the clean optimum after recovery"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn outlier_options_are_checked_and_trusted_factors_enter_directly() {
    let s = TestServer::start(&[]);
    let c = client();
    for (body, field) in [
        (
            json!({"kind": "pose_graph_2d", "outliers": "maybe"}),
            "outliers",
        ),
        (
            json!({"kind": "sliding_window", "outliers": "auto"}),
            "outliers",
        ),
    ] {
        let (status, e) = post(&c, &s.url("/v1/sessions"), &body).await;
        assert_eq!(status, 400, "{body}: {e}");
        assert!(
            e["error"]["field"]
                .as_str()
                .unwrap_or("")
                .starts_with(field),
            "{body}: {e}"
        );
    }
    create(
        &c,
        &s,
        &json!({"session": "t", "kind": "pose_graph_2d", "outliers": "auto"}),
    )
    .await;
    let poses: Vec<Value> = (0..6)
        .map(|i| json!({"key": i, "kind": "se2", "value": [i as f64, 0.0, 0.0]}))
        .collect();
    let step = |a: u64, b: u64, x: f64| {
        json!({"type": "between_se2", "keys": [a, b], "measurement": [x, 0.0, 0.0],
               "sigmas": [0.1, 0.1, 0.05]})
    };
    let mut factors: Vec<Value> = (1..6).map(|i| step(i - 1, i, 1.0)).collect();
    let mut trusted = step(0, 5, 5.0);
    trusted["outlier"] = json!("trusted");
    factors.push(trusted);
    let mut bad = step(1, 4, 3.0);
    bad["outlier"] = json!("sometimes");
    let (status, e) = post(
        &c,
        &s.url("/v1/sessions/t/batches"),
        &json!({"variables": poses, "factors": [bad]}),
    )
    .await;
    assert_eq!(status, 400, "{e}");
    assert!(
        e["error"]["field"].as_str().unwrap().contains("outlier"),
        "{e}"
    );
    let (status, ack) = post(
        &c,
        &s.url("/v1/sessions/t/batches"),
        &json!({"variables": poses, "factors": factors}),
    )
    .await;
    assert_eq!(status, 200, "{ack}");
    let (_, report) = get(&c, &s.url("/v1/sessions/t/outliers")).await;
    assert_eq!(
        report["accepted"], 0,
        "the trusted closure is no candidate: {report}"
    );
    assert_eq!(report["pending"], json!([]), "{report}");
    assert_eq!(report["rejected"], json!([]), "{report}");
}
