//! Failover when a host stops answering (issue 52, item 14): an instance that is SIGSTOPped
//! keeps its OS locks (its sessions' and the rpc gateway's) and its zenoh links until their
//! lease runs out. The survivors notice it gone after `--fleet-lease-ms` (default 2 s), see its
//! heartbeat stopped as long, and take over its sessions and the gateway by claiming their next
//! ownership epochs (`journal::takeover`). When it resumes (SIGCONT) it must not acknowledge
//! anything from its old epochs, and what it writes late must not appear.
//!
//! Real processes: three instances on one state directory, a producer writing through the
//! survivors' HTTP, zenoh rpc through a client of a survivor.

use crate::common;

use std::time::{Duration, Instant};

use common::fleet::{gateways, zenoh_replies, Fleet};
use common::server::zenoh_session;
use serde_json::{json, Value};

fn signal(pid: u32, signal: libc::c_int) {
    // SAFETY: a plain system call on a child process of this test.
    let done = unsafe { libc::kill(pid as libc::pid_t, signal) };
    assert_eq!(done, 0, "kill({pid}, {signal})");
}

fn client() -> reqwest::Client {
    reqwest::Client::builder()
        .timeout(Duration::from_secs(1))
        .build()
        .unwrap()
}

/// Batch `k` of the producer `robot`: pose `k` and the odometry from pose `k - 1` (the first
/// also the fixed pose 0).
fn batch(k: u64) -> Value {
    let mut variables = vec![json!({"key": k, "kind": "se2", "value": [k as f64, 0, 0]})];
    if k == 1 {
        variables.push(json!({"key": 0, "kind": "se2", "value": [0, 0, 0], "fixed": true}));
    }
    json!({
        "variables": variables,
        "factors": [{"type": "between_se2", "keys": [k - 1, k], "measurement": [1, 0, 0],
                     "sigmas": [0.1, 0.1, 0.05]}],
        "producer": "robot", "producer_seq": k,
    })
}

/// Sends batch `k` to session `name` through the instances at `via` in turn, again and again
/// (the same producer sequence: a repeat is answered with its first acknowledgement) until one
/// acknowledges it; returns the acknowledgement.
async fn acknowledged(c: &reqwest::Client, via: &[String], name: &str, k: u64) -> Value {
    let deadline = Instant::now() + Duration::from_secs(30);
    for attempt in 0.. {
        let url = format!("{}/v1/sessions/{name}/batches", via[attempt % via.len()]);
        if let Ok(answer) = c.post(&url).json(&batch(k)).send().await {
            let status = answer.status().as_u16();
            if let Ok(body) = answer.json::<Value>().await {
                if status == 200 {
                    return body;
                }
                assert!(
                    status == 503 || status == 502 || status == 504,
                    "batch {k}: {status} {body}"
                );
            }
        }
        assert!(Instant::now() < deadline, "batch {k} never acknowledged");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    unreachable!()
}

async fn stats(c: &reqwest::Client, via: &str, name: &str) -> Value {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let url = format!("{via}/v1/sessions/{name}");
        if let Ok(answer) = c.get(&url).send().await {
            if answer.status() == 200 {
                return answer.json().await.unwrap();
            }
        }
        assert!(Instant::now() < deadline, "{name} never readable via {via}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Replies to one `health` on `factord/rpc` until one instance answers; never two.
async fn rpc_served_within(z: &zenoh::Session, since: Instant, within: Duration) -> Duration {
    loop {
        let got = zenoh_replies(z, "factord/rpc", &json!({"op": "health"})).await;
        match got.len() {
            0 => assert!(since.elapsed() < within, "no rpc gateway after {within:?}"),
            1 => return since.elapsed(),
            n => panic!("{n} replies to one health query: {got:?}"),
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_stopped_host_is_taken_over_and_acknowledges_nothing_when_it_resumes() {
    let fleet = Fleet::start(3, &[]);
    let z = zenoh_session("client", "connect", &fleet.instance(1).zenoh).await;
    fleet.wait_settled(&z).await;
    let deadline = Instant::now() + Duration::from_secs(10);
    while gateways(&z).await != ["f1"] {
        assert!(Instant::now() < deadline, "f1 never became the gateway");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // A session f1 owns, written through the survivors (they forward to f1).
    let name = (0..)
        .map(|i| format!("robot{i}"))
        .find(|n| fleet.owner(n) == 0)
        .unwrap();
    let survivors = vec![
        fleet.instance(1).http.clone(),
        fleet.instance(2).http.clone(),
    ];
    let c = client();
    let created = c
        .post(format!("{}/v1/sessions", survivors[0]))
        .json(&json!({"session": name, "kind": "pose_graph_2d",
                      "auto_optimize": {"policy": "manual"}}))
        .timeout(Duration::from_secs(15))
        .send()
        .await
        .unwrap();
    assert_eq!(created.status(), 201, "{}", fleet.logs());
    let mut sequences = Vec::new();
    for k in 1..=20 {
        let ack = acknowledged(&c, &survivors, &name, k).await;
        sequences.push(ack["sequence"].as_u64().unwrap());
    }

    let stopped_at = Instant::now();
    signal(fleet.instance(0).pid, libc::SIGSTOP);
    // The first write after the stop, and the rpc, measured from the stop, side by side.
    let (ack, rpc_after) = tokio::join!(
        acknowledged(&c, &survivors, &name, 21),
        rpc_served_within(&z, stopped_at, Duration::from_secs(30)),
    );
    let write_after = stopped_at.elapsed();
    sequences.push(ack["sequence"].as_u64().unwrap());
    eprintln!(
        "SIGSTOP of the owner and gateway: a write acknowledged by a survivor after \
         {write_after:?}, the rpc served again after {rpc_after:?}"
    );
    assert!(
        write_after < Duration::from_secs(10),
        "{write_after:?} (target 5 s): {}",
        fleet.logs()
    );
    for k in 22..=30 {
        let ack = acknowledged(&c, &survivors, &name, k).await;
        sequences.push(ack["sequence"].as_u64().unwrap());
    }
    let gateway = gateways(&z).await;
    assert!(gateway == ["f2"] || gateway == ["f3"], "{gateway:?}");

    // A write sent to the stopped instance itself: it reaches it when it resumes.
    let stale_client = reqwest::Client::new();
    let stale_url = fleet
        .instance(0)
        .url(&format!("/v1/sessions/{name}/batches"));
    let stale_batch = json!({"variables": [{"key": 1000, "kind": "se2", "value": [9, 9, 0]}],
                             "factors": [{"type": "between_se2", "keys": [0, 1000],
                                          "measurement": [9, 9, 0], "sigmas": [1, 1, 1]}],
                             "producer": "stale", "producer_seq": 1});
    let stale = tokio::spawn(async move {
        let answer = stale_client
            .post(stale_url)
            .json(&stale_batch)
            .timeout(Duration::from_secs(30))
            .send()
            .await
            .unwrap();
        let status = answer.status().as_u16();
        (status, answer.json::<Value>().await.unwrap_or(Value::Null))
    });
    tokio::time::sleep(Duration::from_millis(300)).await;
    signal(fleet.instance(0).pid, libc::SIGCONT);
    let (stale_status, stale_answer) = stale.await.unwrap();
    eprintln!("the write sent to the stopped instance, answered on resuming: {stale_status} {stale_answer}");

    // The fleet settles with f1 back: commands run once, writes go on.
    fleet.wait_settled(&z).await;
    for _ in 0..20 {
        let got = zenoh_replies(&z, "factord/rpc", &json!({"op": "health"})).await;
        assert!(got.len() <= 1, "{} replies to one health query", got.len());
    }
    rpc_served_within(&z, Instant::now(), Duration::from_secs(20)).await;
    let all: Vec<String> = (0..3).map(|i| fleet.instance(i).http.clone()).collect();
    for k in 31..=35 {
        let ack = acknowledged(&c, &all, &name, k).await;
        sequences.push(ack["sequence"].as_u64().unwrap());
    }

    // Every acknowledged batch is there once, in order; the stale write only if acknowledged.
    let stale_applied = stale_status == 200;
    if !stale_applied {
        assert!(
            stale_answer["error"]["code"] == "ownership_lost"
                || stale_answer["error"]["code"] == "session_moving",
            "{stale_status} {stale_answer}"
        );
    }
    let expected: Vec<u64> = (1..=35)
        .map(|s| s + u64::from(stale_applied && s > 30))
        .collect();
    assert_eq!(sequences, expected, "no sequence skipped or given twice");
    let s = stats(&c, &all[1], &name).await;
    let batches = 35 + u64::from(stale_applied);
    assert_eq!(s["sequence"].as_u64().unwrap(), batches, "{s}");
    assert_eq!(s["num_variables"].as_u64().unwrap(), batches + 1, "{s}");
    let stale_progress: Value = c
        .get(format!("{}/v1/sessions/{name}/producers/stale", all[2]))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(
        stale_progress["accepted_through"],
        u64::from(stale_applied),
        "the stale write is there exactly when it was acknowledged: {stale_progress}"
    );
    let logs = fleet.logs();
    assert!(!logs.contains("panicked"), "{logs}");
    assert!(logs.contains("taking over from `f1`"), "{logs}");
}
