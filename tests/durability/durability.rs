//! Durable sessions against the real binary: `kill -9` during streaming, restart on the same
//! state directory, and every acknowledged batch is there and the estimate re-converges.

use crate::common;

use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use common::server::{client, create, g2o_batches, get, post, recovered, TestServer};
use serde_json::{json, Value};

fn config_file(dir: &Path, snapshot_every: u64) -> String {
    let path = dir.join("factord.json");
    std::fs::write(
        &path,
        json!({"journal": {"snapshot_every": snapshot_every}}).to_string(),
    )
    .unwrap();
    path.display().to_string()
}

#[tokio::test(flavor = "multi_thread")]
async fn kill_9_while_streaming_loses_no_acknowledged_batch() {
    const KILLS: usize = 20;
    let text = common::synthetic_manhattan(3000, 11);
    let batches = g2o_batches(&text);
    // The optimum an uninterrupted solve reaches, for the re-convergence check.
    let reference = {
        let path = common::temp_dir("durability-ref").join("g.g2o");
        std::fs::write(&path, &text).unwrap();
        let mut g = factord::io::load(&path, None).unwrap();
        factord::solver::optimize(&mut g.problem, &Default::default(), &mut |_| {
            std::ops::ControlFlow::Continue(())
        })
        .unwrap()
        .final_chi2
    };
    let state = common::temp_dir("durability-state");
    let config = config_file(state.parent().unwrap(), 150);
    let extra = ["--no-zenoh", "--config", config.as_str(), "--log", "info"];
    let c = client();
    let mut rng = 0x9e37_79b9_7f4a_7c15u64;
    let mut next_random = move || {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        rng
    };
    let acked: Arc<Mutex<Vec<u64>>> = Arc::new(Mutex::new(Vec::new()));
    let (mut worst_recovery, mut recovered_sizes) = (0.0f64, Vec::new());
    let mut kills_mid_stream = 0;
    for cycle in 0..=KILLS {
        let started = Instant::now();
        let s = TestServer::start_at(&state, &extra, &[]);
        let resume = if cycle == 0 {
            create(
                &c,
                &s,
                &json!({"session": "robot", "kind": "pose_graph_2d"}),
            )
            .await;
            0
        } else {
            let (stats, seconds) = recovered(&c, &s, "robot", started).await;
            let sequence = stats["sequence"].as_u64().unwrap();
            let last_acked = acked.lock().unwrap().last().copied().unwrap_or(0);
            // Everything acknowledged is there (a batch journalled but not yet acknowledged
            // when the kill came may be there too: the client resumes after the server's).
            assert!(
                sequence >= last_acked,
                "cycle {cycle}: sequence {sequence} < acked {last_acked}"
            );
            let (_, estimate) = get(&c, &s.url("/v1/sessions/robot/estimate")).await;
            let keys: Vec<u64> = estimate["variables"]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v["key"].as_u64().unwrap())
                .collect();
            assert_eq!(keys, (0..sequence).collect::<Vec<_>>(), "cycle {cycle}");
            worst_recovery = worst_recovery.max(seconds);
            recovered_sizes.push((sequence, stats["num_factors"].as_u64().unwrap(), seconds));
            sequence as usize
        };
        if cycle == KILLS {
            // Stream the rest, and the estimate converges to the uninterrupted optimum.
            for b in &batches[resume..] {
                let (status, v) = post(&c, &s.url("/v1/sessions/robot/batches"), b).await;
                assert_eq!(status, 200, "{v}");
            }
            let (status, v) = post(
                &c,
                &s.url("/v1/sessions/robot/optimize?wait=true"),
                &json!(null),
            )
            .await;
            assert_eq!(status, 200, "{v}");
            let chi2 = v["stats"]["chi2"].as_f64().unwrap();
            // Both stop at the default function tolerance (1e-6 relative decrease) from
            // different starting points: equal to within a few of those.
            assert!(
                (chi2 - reference).abs() <= 1e-5 * reference,
                "{chi2} vs {reference}"
            );
            assert_eq!(v["stats"]["num_variables"], 3000);
            s.assert_no_panic();
            assert_eq!(kills_mid_stream, KILLS);
            println!(
                "{KILLS} kills; acknowledged batches {}; lost 0; recovery (restart to writable) worst {:.3}s; per restart (sequence, factors, seconds): {recovered_sizes:?}",
                acked.lock().unwrap().len(),
                worst_recovery
            );
            return;
        }
        // Stream from where the server is, and kill it at a random moment.
        let feeder = {
            let (c, url, acked) = (
                c.clone(),
                s.url("/v1/sessions/robot/batches"),
                Arc::clone(&acked),
            );
            let todo: Vec<Value> = batches[resume..].to_vec();
            tokio::spawn(async move {
                for b in todo {
                    match c.post(&url).json(&b).send().await {
                        Ok(r) if r.status() == 200 => {
                            let v: Value = match r.json().await {
                                Ok(v) => v,
                                Err(_) => return, // killed while answering: not acknowledged
                            };
                            acked.lock().unwrap().push(v["sequence"].as_u64().unwrap());
                        }
                        _ => return,
                    }
                }
            })
        };
        // Kill after a random number of further acknowledgements, mid-stream.
        let target = acked.lock().unwrap().len() + 20 + (next_random() % 130) as usize;
        let deadline = Instant::now() + Duration::from_secs(30);
        while acked.lock().unwrap().len() < target && !feeder.is_finished() {
            assert!(Instant::now() < deadline, "streaming stalled");
            tokio::time::sleep(Duration::from_micros(200)).await;
        }
        let log = s.kill();
        assert!(!log.contains("panicked"), "{log}");
        let _ = feeder.await;
        kills_mid_stream += usize::from(resume + 20 < batches.len());
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_torn_journal_tail_is_cut_and_the_rest_recovered() {
    let state = common::temp_dir("durability-torn");
    let c = client();
    let batches = g2o_batches(&common::synthetic_manhattan(60, 5));
    {
        let s = TestServer::start_at(&state, &["--no-zenoh"], &[]);
        let (status, _) = post(
            &c,
            &s.url("/v1/sessions"),
            &json!({"session": "torn", "kind": "pose_graph_2d"}),
        )
        .await;
        assert_eq!(status, 201);
        for b in &batches {
            assert_eq!(
                post(&c, &s.url("/v1/sessions/torn/batches"), b).await.0,
                200
            );
        }
        s.kill();
    }
    // A crash in the middle of the last append: half of its record is on disk.
    let journal = state.join("sessions/torn/journal.log");
    let bytes = std::fs::read(&journal).unwrap();
    let (end, last_len) = {
        // Walk the records to find where the last one starts; a zero length is their end (the
        // file is grown with zeros ahead of them).
        let (mut at, mut last) = (0usize, 0usize);
        while at + 8 <= bytes.len() {
            let len = u32::from_le_bytes(bytes[at..at + 4].try_into().unwrap()) as usize;
            if len == 0 {
                break;
            }
            last = at;
            at += 8 + len;
        }
        (at, at - last)
    };
    std::fs::write(&journal, &bytes[..end - last_len / 2]).unwrap();
    let s = TestServer::start_at(&state, &["--no-zenoh"], &[]);
    let (stats, _) = recovered(&c, &s, "torn", Instant::now()).await;
    assert_eq!(stats["sequence"], 59, "{stats}");
    assert_eq!(stats["num_variables"], 59);
    assert!(s.stderr().contains("truncated_bytes"), "{}", s.stderr());
    // The session goes on from there, and deleting it removes its files.
    assert_eq!(
        post(&c, &s.url("/v1/sessions/torn/batches"), &batches[59])
            .await
            .0,
        200
    );
    let deleted = c.delete(s.url("/v1/sessions/torn")).send().await.unwrap();
    assert_eq!(deleted.status(), 200);
    assert!(!state.join("sessions/torn").exists());
    s.assert_no_panic();
}

/// A factor whose residual is not finite where it would start is refused before anything is
/// journalled or applied (it used to pass validation and then fail inside the problem), over
/// HTTP and zenoh; the session and its journal stay good across a restart.
#[tokio::test(flavor = "multi_thread")]
async fn a_non_finite_residual_is_refused_before_the_journal() {
    let state = common::temp_dir("durability-nonfinite");
    let c = client();
    let s = TestServer::start_at(&state, &[], &[]);
    for (name, kind) in [("ba", "bundle_adjustment"), ("pg", "pose_graph_2d")] {
        create(&c, &s, &json!({"session": name, "kind": kind})).await;
    }
    // A point exactly at the camera's centre: depth 0.
    let ba = json!({
        "variables": [
            {"key": 0, "kind": "snavely_camera", "value": [0, 0, 0, 0, 0, 0, 500, 0, 0]},
            {"key": 1, "kind": "point3", "value": [0, 0, 0]}],
        "factors": [{"type": "reprojection_snavely", "keys": [0, 1], "measurement": [1, 2], "sigmas": [1, 1]}]});
    // Poses so far apart that their difference overflows.
    let pg = json!({
        "variables": [
            {"key": 0, "kind": "se2", "value": [1e308, 0, 0]},
            {"key": 1, "kind": "se2", "value": [-1e308, 0, 0]}],
        "factors": [{"type": "between_se2", "keys": [0, 1], "measurement": [1, 0, 0], "sigmas": [1, 1, 1]}]});
    for (name, batch) in [("ba", &ba), ("pg", &pg)] {
        let (status, v) = post(&c, &s.url(&format!("/v1/sessions/{name}/batches")), batch).await;
        assert_eq!(status, 422, "{name}: {v}");
        assert_eq!(v["error"]["code"], "non_finite_residual");
        assert_eq!(v["error"]["field"], "factors[0]");
    }
    let z = common::server::zenoh_peer(&s.zenoh).await;
    let err = common::server::zenoh_get(
        &z,
        "factord/rpc",
        Some(&json!({"op": "apply_batch", "session": "pg", "batch": pg})),
    )
    .await
    .unwrap_err();
    assert_eq!(err["error"]["code"], "non_finite_residual");
    z.close().await.unwrap();
    // Nothing was applied; good batches still are.
    let good = json!({"variables": [{"key": 0, "kind": "se2", "value": [0, 0, 0]}]});
    assert_eq!(
        post(&c, &s.url("/v1/sessions/pg/batches"), &good).await.0,
        200
    );
    let (_, stats) = get(&c, &s.url("/v1/sessions/pg")).await;
    assert_eq!(
        (stats["sequence"].as_u64(), stats["num_variables"].as_u64()),
        (Some(1), Some(1))
    );
    s.assert_no_panic();
    s.kill();
    let s = TestServer::start_at(&state, &[], &[]);
    let (stats, _) = recovered(&c, &s, "pg", Instant::now()).await;
    assert_eq!(stats["num_variables"], 1);
    s.assert_no_panic();
}

/// A sliding window is rebuilt by replaying its fusion messages: after `kill -9` its keyframes
/// and newest state are those acknowledged before the kill.
#[tokio::test(flavor = "multi_thread")]
async fn a_sliding_window_comes_back_after_kill_9() {
    let Some(inputs) = common::fusion::inputs(6.0, 10) else {
        return;
    };
    let state = common::temp_dir("durability-window");
    let c = client();
    let s = TestServer::start_at(&state, &["--no-zenoh"], &[]);
    create(
        &c,
        &s,
        &json!({"session": "robot", "kind": "sliding_window"}),
    )
    .await;
    let url = s.url("/v1/sessions/robot/fusion");
    let start = json!({"messages": [common::fusion::start_message(&inputs)]});
    assert_eq!(post(&c, &url, &start).await.0, 200);
    let mut latest = Value::Null;
    for batch in common::fusion::keyframe_batches(&inputs) {
        let (status, reply) = post(&c, &url, &json!({"messages": batch})).await;
        assert_eq!(status, 200, "{reply}");
        latest = reply["latest"].clone();
    }
    let (_, before) = get(&c, &s.url("/v1/sessions/robot/graph")).await;
    s.kill();

    let s = TestServer::start_at(&state, &["--no-zenoh"], &[]);
    recovered(&c, &s, "robot", Instant::now()).await;
    let (_, after) = get(&c, &s.url("/v1/sessions/robot/graph")).await;
    assert_eq!(
        after["poses"].as_array().unwrap().len(),
        before["poses"].as_array().unwrap().len()
    );
    let newest = after["poses"].as_array().unwrap().last().unwrap();
    assert_eq!(newest["key"], latest["key"]);
    for axis in 0..3 {
        let (a, b) = (
            newest["position"][axis].as_f64().unwrap(),
            latest["position"][axis].as_f64().unwrap(),
        );
        assert!((a - b).abs() < 1e-9, "axis {axis}: {a} vs {b}");
    }
    // And it goes on taking messages.
    let url = s.url("/v1/sessions/robot/fusion");
    let (status, v) = post(&c, &url, &json!({"messages": []})).await;
    assert_eq!(status, 200, "{v}");
    s.assert_no_panic();
}

/// A journal entry that no longer replays (here: written by hand, checksum intact, naming a
/// variable that does not exist) stops the recovery there. The session keeps what was rebuilt,
/// is read-only for good (409 `session_corrupt`, `corrupt` in its statistics; before, it stayed
/// `recovering` and answered 503 "try again shortly" forever, DELETE included), says why in
/// `last_error`, and can be deleted. A session whose `session.json` cannot be read is left on
/// disk and not listed. Other sessions recover as usual, and the server starts.
#[tokio::test(flavor = "multi_thread")]
async fn a_journal_entry_that_does_not_replay_leaves_the_session_read_only() {
    let state = common::temp_dir("durability-stuck");
    let c = client();
    let s = TestServer::start_at(&state, &["--no-zenoh"], &[]);
    for name in ["stuck", "fine", "unreadable"] {
        let request = json!({"session": name, "kind": "pose_graph_2d", "auto_optimize": {"policy": "manual"}});
        create(&c, &s, &request).await;
        let batch = json!({"variables": [{"key": 0, "kind": "se2", "value": [0, 0, 0]}]});
        let url = s.url(&format!("/v1/sessions/{name}/batches"));
        assert_eq!(post(&c, &url, &batch).await.0, 200);
    }
    s.kill();
    let bad: factord::journal::Entry = serde_json::from_value(json!({"op": "batch", "sequence": 2,
        "batch": {"factors": [{"type": "prior_se2", "keys": [99], "measurement": [0, 0, 0], "sigmas": [1, 1, 1]}]}}))
    .unwrap();
    let journal = state.join("sessions/stuck/journal.log");
    let mut log =
        factord::journal::log::LogWriter::open(&journal, factord::journal::log::Fsync::Always)
            .unwrap();
    log.append(&serde_json::to_vec(&bad).unwrap()).unwrap();
    drop(log);
    let identity = state.join("sessions/unreadable/session.json");
    std::fs::write(&identity, "{").unwrap();

    let s = TestServer::start_at(&state, &["--no-zenoh"], &[]);
    let (fine, _) = recovered(&c, &s, "fine", Instant::now()).await;
    assert_eq!(fine["num_variables"], 1, "{fine}");
    let deadline = Instant::now() + Duration::from_secs(20);
    let stuck = loop {
        let stats = get(&c, &s.url("/v1/sessions/stuck")).await.1;
        if stats["corrupt"] == true {
            break stats;
        }
        assert!(Instant::now() < deadline, "no recovery error: {stats}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    let error = stuck["last_error"].as_str().unwrap();
    assert!(
        error.starts_with("recovery stopped") && error.contains("entry 1"),
        "{stuck}"
    );
    assert_eq!(stuck["recovering"], false, "{stuck}");
    assert_eq!(
        (stuck["sequence"].as_u64(), stuck["num_variables"].as_u64()),
        (Some(1), Some(1)),
        "kept as far as it got: {stuck}"
    );
    let batch = json!({"variables": [{"key": 1, "kind": "se2", "value": [0, 0, 0]}]});
    let (status, v) = post(&c, &s.url("/v1/sessions/stuck/batches"), &batch).await;
    assert_eq!(
        (status, v["error"]["code"].as_str()),
        (409, Some("session_corrupt")),
        "{v}"
    );
    let (status, _) = get(&c, &s.url("/v1/sessions/unreadable")).await;
    assert_eq!(status, 404);
    assert!(identity.exists(), "its files are left for an operator");
    let deleted = c.delete(s.url("/v1/sessions/stuck")).send().await.unwrap();
    assert_eq!(deleted.status(), 200);
    assert!(!state.join("sessions/stuck").exists());
    s.assert_no_panic();
}

/// Numbers come back bit for bit: as the estimate reads them after they are sent, and after
/// `kill -9` from the snapshot and the journal. serde_json's default float parser reads about 1
/// double in 10 one unit in the last place off (`180.17933438838418` as …415), so a client's
/// values and every replayed journal entry used to change.
#[tokio::test(flavor = "multi_thread")]
async fn sent_numbers_come_back_bit_for_bit_also_after_kill_9() {
    let state = common::temp_dir("durability-bits");
    let config = config_file(&common::temp_dir("durability-bits-config"), 2);
    let c = client();
    // Doubles spread over [-1000, 1000] and headings over (-3, 3), as a client would send them
    // (the shortest text that reads back as each).
    let mut seed: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut next = |scale: f64| {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        ((seed >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0) * scale
    };
    let sent: Vec<[f64; 3]> = (0..400)
        .map(|_| [next(1000.0), next(1000.0), next(3.0)])
        .collect();
    let check = |estimate: &Value, when: &str| {
        let variables = estimate["variables"].as_array().unwrap();
        assert_eq!(variables.len(), sent.len(), "{when}");
        for v in variables {
            let key = v["key"].as_u64().unwrap() as usize;
            let got: Vec<u64> = v["value"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap().to_bits())
                .collect();
            let want: Vec<u64> = sent[key].iter().map(|x| x.to_bits()).collect();
            assert_eq!(got, want, "{when}: variable {key}: {v}");
        }
    };
    {
        let s = TestServer::start_at(&state, &["--no-zenoh", "--config", &config], &[]);
        create(
            &c,
            &s,
            &json!({"session": "bits", "kind": "pose_graph_2d", "auto_optimize": {"policy": "manual"}}),
        )
        .await;
        for (i, chunk) in sent.chunks(50).enumerate() {
            let variables: Vec<Value> = chunk
                .iter()
                .enumerate()
                .map(|(j, v)| json!({"key": i * 50 + j, "kind": "se2", "value": v, "fixed": true}))
                .collect();
            let url = s.url("/v1/sessions/bits/batches");
            let (status, ack) = post(&c, &url, &json!({ "variables": variables })).await;
            assert_eq!(status, 200, "{ack}");
        }
        check(
            &get(&c, &s.url("/v1/sessions/bits/estimate")).await.1,
            "sent",
        );
        s.kill();
    }
    let s = TestServer::start_at(&state, &["--no-zenoh", "--config", &config], &[]);
    recovered(&c, &s, "bits", Instant::now()).await;
    check(
        &get(&c, &s.url("/v1/sessions/bits/estimate")).await.1,
        "after kill -9",
    );
    s.assert_no_panic();
}
