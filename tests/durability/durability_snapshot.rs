//! Snapshots are written off the session lock while updates go on (issue 16, item 4): what is
//! journalled while one is being written stays in the journal, so a `kill -9` of the real
//! server at any moment loses no acknowledged batch, and deleting a session while its snapshot
//! is in flight leaves nothing of it behind.

use crate::common;

use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use common::server::{client, create, get, post, recovered, TestServer};
use serde_json::{json, Value};

/// Beside the state directory, named after it: the tests run at once and must not share it.
/// A snapshot every `snapshot_every` entries whatever its size (these tests want them often).
fn config_file(state: &Path, snapshot_every: u64) -> String {
    let path = state.with_extension("json");
    std::fs::write(
        &path,
        json!({"journal": {"snapshot_every": snapshot_every, "snapshot_journal_share": 0.0}})
            .to_string(),
    )
    .unwrap();
    path.display().to_string()
}

/// Poses `0..n` along a line with odometry between them, in one batch.
fn chain(n: u64) -> Value {
    let variables: Vec<Value> = (0..n)
        .map(|k| json!({"key": k, "kind": "se2", "value": [k as f64, 0.0, 0.0], "fixed": k == 0}))
        .collect();
    let factors: Vec<Value> = (1..n)
        .map(|k| json!({"type": "between_se2", "keys": [k - 1, k], "measurement": [1.0, 0.0, 0.0], "sigmas": [0.1, 0.1, 0.05]}))
        .collect();
    json!({"variables": variables, "factors": factors})
}

/// Pose `k` from `k - 1`, its value predicted from the odometry.
fn next_pose(k: u64) -> Value {
    json!({"variables": [{"key": k, "kind": "se2"}],
        "factors": [{"type": "between_se2", "keys": [k - 1, k], "measurement": [1.0, 0.0, 0.0], "sigmas": [0.1, 0.1, 0.05]}]})
}

fn snapshot_sequence(state: &Path, name: &str) -> Option<u64> {
    let text = std::fs::read(state.join(format!("sessions/{name}/snapshot.json"))).ok()?;
    // The snapshot inside its checksum envelope.
    serde_json::from_slice::<Value>(&text).ok()?["snapshot"]["sequence"].as_u64()
}

/// The sequences of the snapshots a server log shows: written ones, and those a restart
/// recovered from.
fn snapshot_sequences(log: &str) -> std::collections::BTreeSet<u64> {
    let after = |line: &str, marker: &str| {
        let rest = &line[line.find(marker)? + marker.len()..];
        let digits: String = rest.chars().take_while(char::is_ascii_digit).collect();
        digits.parse().ok()
    };
    log.lines()
        .filter_map(|line| {
            if line.contains("snapshot written") {
                after(line, "sequence=")
            } else {
                after(line, "recovered from snapshot Some(")
            }
        })
        .collect()
}

/// A session large enough that a snapshot takes a while (20 000 poses), streamed into with a
/// snapshot every 40 entries, killed at random moments: every acknowledged pose comes back, and
/// the restarts come back from a snapshot plus the journal after it (entries journalled while a
/// snapshot was written are kept by its compaction; emptying the journal, as a snapshot under
/// the lock could, would lose them and fail here).
#[tokio::test(flavor = "multi_thread")]
async fn kill_9_while_snapshots_are_written_loses_no_acknowledged_batch() {
    const BASE: u64 = 20_000;
    const KILLS: usize = 6;
    let state = common::temp_dir("snapshot-stream");
    let config = config_file(&state, 40);
    let extra = ["--no-zenoh", "--config", config.as_str(), "--log", "info"];
    let c = client();
    let acked: Arc<Mutex<u64>> = Arc::new(Mutex::new(0));
    let mut rng = 0x2545_f491_4f6c_dd1du64;
    let mut behind = Vec::new();
    for cycle in 0..=KILLS {
        let s = TestServer::start_at(&state, &extra, &[]);
        let next = if cycle == 0 {
            create(
                &c,
                &s,
                &json!({"session": "big", "kind": "pose_graph_2d", "auto_optimize": {"policy": "manual"}}),
            )
            .await;
            let (status, v) = post(&c, &s.url("/v1/sessions/big/batches"), &chain(BASE)).await;
            assert_eq!(status, 200, "{v}");
            *acked.lock().unwrap() = 1;
            BASE
        } else {
            let (stats, _) = recovered(&c, &s, "big", Instant::now()).await;
            let sequence = stats["sequence"].as_u64().unwrap();
            let last_acked = *acked.lock().unwrap();
            assert!(
                sequence >= last_acked,
                "cycle {cycle}: sequence {sequence} < acknowledged {last_acked}\n{}",
                s.stderr()
            );
            // Sequence 1 was the chain of BASE poses, then one pose per batch.
            let poses = BASE + sequence - 1;
            assert_eq!(stats["num_variables"].as_u64(), Some(poses), "{stats}");
            assert_eq!(stats["num_factors"].as_u64(), Some(poses - 1), "{stats}");
            let (_, tail) = get(
                &c,
                &s.url(&format!("/v1/sessions/big/estimate?from={}", poses - 5)),
            )
            .await;
            let keys: Vec<u64> = tail["variables"]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v["key"].as_u64().unwrap())
                .collect();
            assert_eq!(keys, (poses - 5..poses).collect::<Vec<_>>(), "{tail}");
            if let Some(snapshot) = snapshot_sequence(&state, "big") {
                behind.push(last_acked.saturating_sub(snapshot));
            }
            if cycle == KILLS {
                s.assert_no_panic();
                // A snapshot renamed into place just before a kill may not have logged its
                // line yet; the restart after it names it. Both count, once per sequence.
                let log = s.stderr();
                let written = snapshot_sequences(&log);
                println!("{} snapshots written over {KILLS} kills", written.len());
                assert!(written.len() >= KILLS, "{written:?}\n{log}");
                break;
            }
            poses
        };
        let feeder = {
            let (c, url, acked) = (
                c.clone(),
                s.url("/v1/sessions/big/batches"),
                Arc::clone(&acked),
            );
            tokio::spawn(async move {
                for k in next.. {
                    match c.post(&url).json(&next_pose(k)).send().await {
                        Ok(r) if r.status() == 200 => match r.json::<Value>().await {
                            Ok(v) => *acked.lock().unwrap() = v["sequence"].as_u64().unwrap(),
                            Err(_) => return,
                        },
                        _ => return,
                    }
                }
            })
        };
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        // 200–600 batches, at a snapshot every 40 entries: long enough for one snapshot of
        // 20 000 poses (20–50 ms) to finish in every cycle on a fast machine too (with 80–240
        // some cycles acknowledged all their batches within one snapshot's write), while the
        // kill still lands anywhere relative to the ones in flight.
        let target = *acked.lock().unwrap() + 200 + rng % 400;
        let deadline = Instant::now() + Duration::from_secs(60);
        // The first kill waits for the first snapshot too (a snapshot replaces the last one by
        // a rename, so one exists at every restart after it): on a loaded machine the first
        // snapshot of 20 000 poses could still be being written when the first target is
        // reached, and that restart would have no snapshot to come back from.
        let first_snapshot = state.join("sessions/big/snapshot.json");
        while *acked.lock().unwrap() < target || (cycle == 0 && !first_snapshot.exists()) {
            assert!(
                Instant::now() < deadline,
                "streaming stalled\n{}",
                s.stderr()
            );
            tokio::time::sleep(Duration::from_micros(300)).await;
        }
        let log = s.kill();
        assert!(!log.contains("panicked"), "{log}");
        let _ = feeder.await;
    }
    println!("acknowledged batches after the last snapshot at each kill: {behind:?}");
    assert_eq!(behind.len(), KILLS);
    assert!(
        behind.iter().any(|&b| b > 0),
        "restarts replayed journal entries after their snapshot: {behind:?}"
    );
}

/// A session deleted while its snapshot is being written leaves no file behind, and a session
/// of the same name created right after starts empty, on disk too.
#[tokio::test(flavor = "multi_thread")]
async fn deleting_a_session_while_its_snapshot_is_written_resurrects_nothing() {
    let state = common::temp_dir("snapshot-delete");
    let config = config_file(&state, 2);
    let extra = ["--no-zenoh", "--config", config.as_str(), "--log", "info"];
    let c = client();
    let s = TestServer::start_at(&state, &extra, &[]);
    let request =
        json!({"session": "gone", "kind": "pose_graph_2d", "auto_optimize": {"policy": "manual"}});
    for round in 0..5 {
        create(&c, &s, &request).await;
        let url = s.url("/v1/sessions/gone/batches");
        assert_eq!(post(&c, &url, &chain(20_000)).await.0, 200);
        // The second entry starts a snapshot of 20 000 poses; delete while it is written.
        assert_eq!(post(&c, &url, &next_pose(20_000)).await.0, 200);
        let deleted = c.delete(s.url("/v1/sessions/gone")).send().await.unwrap();
        assert_eq!(deleted.status(), 200, "round {round}");
        create(&c, &s, &request).await;
        let one = json!({"variables": [{"key": 0, "kind": "se2", "value": [0, 0, 0]}]});
        assert_eq!(post(&c, &url, &one).await.0, 200);
        tokio::time::sleep(Duration::from_millis(300)).await;
        assert!(
            !state.join("sessions/gone/snapshot.json").exists(),
            "round {round}: the deleted session's snapshot was written into the new one's directory"
        );
        let (_, stats) = get(&c, &s.url("/v1/sessions/gone")).await;
        assert_eq!(stats["num_variables"], 1, "{stats}");
        let deleted = c.delete(s.url("/v1/sessions/gone")).send().await.unwrap();
        assert_eq!(deleted.status(), 200);
    }
    create(&c, &s, &request).await;
    let one = json!({"variables": [{"key": 7, "kind": "se2", "value": [0, 0, 0]}]});
    assert_eq!(
        post(&c, &s.url("/v1/sessions/gone/batches"), &one).await.0,
        200
    );
    s.assert_no_panic();
    s.kill();
    let s = TestServer::start_at(&state, &extra, &[]);
    let (stats, _) = recovered(&c, &s, "gone", Instant::now()).await;
    assert_eq!(
        (stats["sequence"].as_u64(), stats["num_variables"].as_u64()),
        (Some(1), Some(1)),
        "{stats}"
    );
    let leftovers: Vec<_> = std::fs::read_dir(state.join("sessions"))
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(
        leftovers,
        ["gone"],
        "no tombstone or stray directory is left"
    );
    s.assert_no_panic();
}

/// Past 1 MiB, a session's next snapshot waits until its journal has grown to
/// `journal.snapshot_journal_share` of the last one (0.25 by default): a large map is not
/// rewritten whole every `snapshot_every` entries. Small batches after a 20 000-pose snapshot
/// leave it where it is; a quarter of its size in journal brings the next.
#[tokio::test(flavor = "multi_thread")]
async fn a_large_session_snapshots_in_proportion_to_its_journal() {
    let state = common::temp_dir("snapshot-share");
    let path = state.with_extension("json");
    std::fs::write(&path, json!({"journal": {"snapshot_every": 2}}).to_string()).unwrap();
    let config = path.display().to_string();
    let extra = ["--no-zenoh", "--config", config.as_str()];
    let c = client();
    let s = TestServer::start_at(&state, &extra, &[]);
    create(
        &c,
        &s,
        &json!({"session": "big", "kind": "pose_graph_2d", "auto_optimize": {"policy": "manual"}}),
    )
    .await;
    let url = s.url("/v1/sessions/big/batches");
    assert_eq!(post(&c, &url, &chain(20_000)).await.0, 200);
    assert_eq!(post(&c, &url, &next_pose(20_000)).await.0, 200);
    snapshot_reaches(&state, 2).await;
    let bytes = std::fs::metadata(state.join("sessions/big/snapshot.json"))
        .unwrap()
        .len();
    assert!(
        bytes > 1 << 20,
        "a snapshot of {bytes} bytes is not a large one"
    );
    // Twenty small batches: ten times `snapshot_every`, far from a quarter of the snapshot.
    for k in 20_001..20_021 {
        assert_eq!(post(&c, &url, &next_pose(k)).await.0, 200);
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert_eq!(
        snapshot_sequence(&state, "big"),
        Some(2),
        "snapshotted again too soon"
    );
    // Over a quarter of the snapshot in journal (a batch's entry is about as large per pose as
    // the snapshot), then one entry more: the next snapshot follows.
    let quarter = 7_000;
    let far: Vec<Value> = (0..quarter)
        .map(|k| json!({"key": 100_000 + k, "kind": "se2", "value": [k as f64, 1.0, 0.0]}))
        .collect();
    let factors: Vec<Value> = (1..quarter)
        .map(|k| json!({"type": "between_se2", "keys": [100_000 + k - 1, 100_000 + k], "measurement": [1.0, 0.0, 0.0], "sigmas": [0.1, 0.1, 0.05]}))
        .chain(std::iter::once(json!({"type": "between_se2", "keys": [0, 100_000], "measurement": [0.0, 1.0, 0.0], "sigmas": [0.1, 0.1, 0.05]})))
        .collect();
    let (status, v) = post(&c, &url, &json!({"variables": far, "factors": factors})).await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(post(&c, &url, &next_pose(20_021)).await.0, 200);
    let (_, stats) = get(&c, &s.url("/v1/sessions/big")).await;
    snapshot_reaches(&state, stats["sequence"].as_u64().unwrap() - 1).await;
    s.assert_no_panic();
    // After a restart the journal is weighed against the snapshot recovered from: small
    // batches leave it where it is again.
    let last = snapshot_sequence(&state, "big");
    s.kill();
    let s = TestServer::start_at(&state, &extra, &[]);
    recovered(&c, &s, "big", Instant::now()).await;
    let url = s.url("/v1/sessions/big/batches");
    for k in 20_022..20_042 {
        assert_eq!(post(&c, &url, &next_pose(k)).await.0, 200);
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert_eq!(
        snapshot_sequence(&state, "big"),
        last,
        "snapshotted again too soon after the restart"
    );
    s.assert_no_panic();
}

/// Waits until session `big`'s snapshot in `state` is of `sequence` or later.
async fn snapshot_reaches(state: &Path, sequence: u64) {
    let deadline = Instant::now() + Duration::from_secs(30);
    while snapshot_sequence(state, "big") < Some(sequence) {
        assert!(
            Instant::now() < deadline,
            "no snapshot of sequence {sequence}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}
