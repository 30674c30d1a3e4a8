//! A fleet of three real `factord serve --fleet` processes on loopback sharing one state
//! directory: sessions spread by placement, HTTP requests to any instance reach the owner,
//! an rpc over zenoh runs once, and after a `kill -9` of one instance its sessions are adopted
//! by the survivors from their journals, with every acknowledged batch there.

use crate::common;

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use common::fleet::{zenoh_replies, Fleet};
use common::server::{g2o_batches, zenoh_peer};
use serde_json::{json, Value};

fn client() -> reqwest::Client {
    reqwest::Client::builder()
        .timeout(Duration::from_secs(20))
        .build()
        .unwrap()
}

/// Sends a request until it is not refused as transient (503: a session moving; a connection
/// failure: an instance dying), for at most `within`; returns the status and JSON answer.
async fn served(
    c: &reqwest::Client,
    method: reqwest::Method,
    url: &str,
    body: Option<&Value>,
    within: Duration,
) -> (u16, Value) {
    let deadline = Instant::now() + within;
    loop {
        let mut request = c.request(method.clone(), url);
        if let Some(b) = body {
            request = request
                .header("content-type", "application/json")
                .body(b.to_string());
        }
        match request.send().await {
            Ok(answer) if answer.status().as_u16() != 503 => {
                let status = answer.status().as_u16();
                let text = answer.text().await.unwrap_or_default();
                return (
                    status,
                    serde_json::from_str(&text).unwrap_or(Value::String(text)),
                );
            }
            Ok(answer) if Instant::now() >= deadline => {
                let text = answer.text().await.unwrap_or_default();
                panic!("{url}: still 503 after {within:?}: {text}");
            }
            Err(e) if Instant::now() >= deadline => panic!("{url}: {e}"),
            _ => tokio::time::sleep(Duration::from_millis(50)).await,
        }
    }
}

async fn post(c: &reqwest::Client, url: &str, body: &Value) -> (u16, Value) {
    served(
        c,
        reqwest::Method::POST,
        url,
        Some(body),
        Duration::from_secs(15),
    )
    .await
}

async fn get(c: &reqwest::Client, url: &str) -> (u16, Value) {
    served(c, reqwest::Method::GET, url, None, Duration::from_secs(15)).await
}

/// The sessions instance `i` holds itself (the loop-guard header asks for its own list only).
async fn local_sessions(c: &reqwest::Client, fleet: &Fleet, i: usize) -> BTreeSet<String> {
    let answer = c
        .get(fleet.instance(i).url("/v1/sessions"))
        .header("factord-forwarded-by", "test")
        .send()
        .await
        .unwrap();
    let v: Value = answer.json().await.unwrap();
    names(&v)
}

fn names(list: &Value) -> BTreeSet<String> {
    list["sessions"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["session"].as_str().unwrap().to_string())
        .collect()
}

/// Two poses and the odometry between them.
fn small_batch(producer: &str, seq: u64) -> Value {
    json!({
        "variables": [{"key": 0, "kind": "se2", "value": [0, 0, 0], "fixed": true},
                      {"key": 1, "kind": "se2", "value": [1, 0, 0]}],
        "factors": [{"type": "between_se2", "keys": [0, 1], "measurement": [1, 0, 0],
                     "sigmas": [0.1, 0.1, 0.05]}],
        "producer": producer, "producer_seq": seq,
    })
}

#[tokio::test(flavor = "multi_thread")]
async fn three_instances_serve_as_one() {
    let fleet = Fleet::start(3, &[]);
    let z = zenoh_peer(&fleet.instance(0).zenoh).await;
    fleet.wait_settled(&z).await;
    let c = client();
    let sessions: Vec<String> = (0..12).map(|i| format!("robot-{i}")).collect();
    // Created through instances in turn, most of them not the owner.
    for (k, name) in sessions.iter().enumerate() {
        let url = fleet.instance(k % 3).url("/v1/sessions");
        let (status, v) = post(&c, &url, &json!({"session": name, "kind": "pose_graph_2d"})).await;
        assert_eq!(status, 201, "{name}: {v}\n{}", fleet.logs());
    }
    // Each lives on its owner, and only there.
    for i in 0..3 {
        let expected: BTreeSet<String> = sessions
            .iter()
            .filter(|s| fleet.owner(s) == i)
            .cloned()
            .collect();
        assert!(
            !expected.is_empty(),
            "placement gave {} nothing",
            fleet.id(i)
        );
        assert_eq!(
            local_sessions(&c, &fleet, i).await,
            expected,
            "{}",
            fleet.id(i)
        );
    }
    let all: BTreeSet<String> = sessions.iter().cloned().collect();
    for i in 0..3 {
        let (_, list) = get(&c, &fleet.instance(i).url("/v1/sessions")).await;
        assert_eq!(names(&list), all, "the list of {}", fleet.id(i));
    }
    // Writes and reads through instances that do not own the session reach its owner.
    for name in &sessions {
        let owner = fleet.owner(name);
        let (writer, reader) = ((owner + 1) % 3, (owner + 2) % 3);
        let url = fleet
            .instance(writer)
            .url(&format!("/v1/sessions/{name}/batches"));
        let (status, ack) = post(&c, &url, &small_batch("r", 1)).await;
        assert_eq!(status, 200, "{ack}");
        assert_eq!(ack["sequence"], 1);
        let url = fleet
            .instance(reader)
            .url(&format!("/v1/sessions/{name}/estimate"));
        let (status, estimate) = get(&c, &url).await;
        assert_eq!(status, 200, "{estimate}");
        assert_eq!(estimate["variables"].as_array().unwrap().len(), 2);
        // A request forwarded once is never forwarded again.
        let answer = c
            .get(fleet.instance(writer).url(&format!("/v1/sessions/{name}")))
            .header("factord-forwarded-by", "test")
            .send()
            .await
            .unwrap();
        assert_eq!(answer.status().as_u16(), 503);
        assert_eq!(answer.headers()["retry-after"], "1");
        let v: Value = answer.json().await.unwrap();
        assert_eq!(v["error"]["code"], "session_moving");
    }

    // zenoh: an unnamed creation over rpc runs on one instance, once.
    let create = json!({"op": "create_session", "kind": "pose_graph_2d"});
    let replies = zenoh_replies(&z, "factord/rpc", &create).await;
    assert_eq!(replies.len(), 1, "{replies:?}");
    let created = replies[0].clone().expect("created");
    let generated = created["session"].as_str().unwrap().to_string();
    let (_, list) = get(&c, &fleet.instance(1).url("/v1/sessions")).await;
    assert_eq!(names(&list).len(), 13, "{list}");
    assert!(names(&list).contains(&generated));
    // A named one goes to its owner, whichever instance the query reached; a second is refused.
    let named = json!({"op": "create_session", "session": "zrobot", "kind": "pose_graph_2d"});
    let first = zenoh_replies(&z, "factord/rpc", &named).await;
    assert!(matches!(first.as_slice(), [Ok(_)]), "{first:?}");
    let again = zenoh_replies(&z, "factord/rpc", &named).await;
    match again.as_slice() {
        [Err(e)] => assert_eq!(e["error"]["code"], "session_exists", "{e}"),
        other => panic!("{other:?}"),
    }
    assert!(local_sessions(&c, &fleet, fleet.owner("zrobot"))
        .await
        .contains("zrobot"));
    // rpc for a session, through whichever instance: answered by its owner.
    let stats = zenoh_replies(
        &z,
        "factord/rpc",
        &json!({"op": "get_stats", "session": "robot-3"}),
    )
    .await;
    assert_eq!(stats.len(), 1);
    assert_eq!(stats[0].as_ref().unwrap()["sequence"], 1);
    let per_session = zenoh_replies(
        &z,
        "factord/robot-3/rpc",
        &json!({"op": "get_stats", "session": "robot-3"}),
    )
    .await;
    assert_eq!(per_session.len(), 1, "{per_session:?}");

    // An event stream (SSE) through an instance that does not own the session is streamed on.
    let name = "robot-5";
    let other = (fleet.owner(name) + 1) % 3;
    let mut events = c
        .get(
            fleet
                .instance(other)
                .url(&format!("/v1/sessions/{name}/events")),
        )
        .send()
        .await
        .unwrap();
    assert_eq!(events.status().as_u16(), 200);
    let url = fleet
        .instance(other)
        .url(&format!("/v1/sessions/{name}/batches"));
    let (status, ack) = post(&c, &url, &json!({"variables": [{"key": 2, "kind": "se2", "value": [2, 0, 0]}],
        "factors": [{"type": "between_se2", "keys": [1, 2], "measurement": [1, 0, 0], "sigmas": [0.1, 0.1, 0.05]}],
        "producer": "r", "producer_seq": 2})).await;
    assert_eq!(status, 200, "{ack}");
    let mut seen = String::new();
    let deadline = Instant::now() + Duration::from_secs(10);
    while !seen.contains("event: ack") {
        let chunk = tokio::time::timeout(Duration::from_secs(10), events.chunk()).await;
        match chunk {
            Ok(Ok(Some(bytes))) => seen.push_str(&String::from_utf8_lossy(&bytes)),
            other => panic!("the forwarded stream ended: {other:?}: {seen}"),
        }
        assert!(
            Instant::now() < deadline,
            "no ack on the forwarded stream: {seen}"
        );
    }
    drop(events);

    // A robot's puts reach the owner, whose acknowledgements come back.
    let name = "zrobot";
    let acks = z
        .declare_subscriber(format!("factord/{name}/out/acks"))
        .await
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(15);
    let ack = loop {
        z.put(
            format!("factord/{name}/in/batch"),
            small_batch("zr", 1).to_string(),
        )
        .await
        .unwrap();
        match tokio::time::timeout(Duration::from_millis(500), acks.recv_async()).await {
            Ok(Ok(sample)) => {
                break serde_json::from_slice::<Value>(&sample.payload().to_bytes()).unwrap()
            }
            _ => assert!(Instant::now() < deadline, "no ack from the owner of {name}"),
        }
    };
    assert_eq!(ack["producer_seq"], 1, "{ack}");
    for i in 0..3 {
        assert!(
            !fleet.instance(i).stderr().contains("panicked"),
            "{}",
            fleet.logs()
        );
    }
}

/// Streams `batches` to session `name` through the instances in `via` in turn, each batch
/// numbered for exactly-once ingest and sent again until acknowledged (through a dying owner
/// and a move); returns the number acknowledged as new.
async fn stream(
    c: reqwest::Client,
    via: Vec<String>,
    name: String,
    batches: Vec<Value>,
    pace: Duration,
) -> usize {
    let mut applied = 0;
    for (k, mut batch) in batches.into_iter().enumerate() {
        batch["producer"] = json!(format!("robot-{name}"));
        batch["producer_seq"] = json!(k + 1);
        let url = format!("{}/v1/sessions/{name}/batches", via[k % via.len()]);
        let (status, ack) = served(
            &c,
            reqwest::Method::POST,
            &url,
            Some(&batch),
            Duration::from_secs(30),
        )
        .await;
        assert_eq!(status, 200, "{name} batch {}: {ack}", k + 1);
        if ack["duplicate"] != true {
            applied += 1;
        }
        tokio::time::sleep(pace).await;
    }
    applied
}

#[tokio::test(flavor = "multi_thread")]
async fn after_a_kill_9_the_survivors_adopt_its_sessions() {
    let mut fleet = Fleet::start(3, &[]);
    let z = zenoh_peer(&fleet.instance(0).zenoh).await;
    fleet.wait_settled(&z).await;
    let c = client();
    let victim = 2;
    let sessions: Vec<String> = (0..9).map(|i| format!("robot-{i}")).collect();
    let on_victim: Vec<String> = sessions
        .iter()
        .filter(|s| fleet.owner(s) == victim)
        .cloned()
        .collect();
    assert!(
        on_victim.len() >= 2,
        "placement gave the victim {on_victim:?}"
    );
    for name in &sessions {
        let (status, v) = post(
            &c,
            &fleet.instance(0).url("/v1/sessions"),
            &json!({"session": name, "kind": "pose_graph_2d"}),
        )
        .await;
        assert_eq!(status, 201, "{v}");
    }
    // Every session streams through the two survivors in turn (mostly not its owner).
    let via = vec![
        fleet.instance(0).http.clone(),
        fleet.instance(1).http.clone(),
    ];
    let per_session = 400;
    let mut streams = Vec::new();
    for (k, name) in sessions.iter().enumerate() {
        let batches = g2o_batches(&common::synthetic_manhattan(per_session, k as u64 + 1));
        let task = stream(
            c.clone(),
            via.clone(),
            name.clone(),
            batches,
            Duration::from_millis(3),
        );
        streams.push((name.clone(), tokio::spawn(task)));
    }
    // Mid-stream: every session has some batches in.
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let (_, s) = get(
            &c,
            &fleet
                .instance(0)
                .url(&format!("/v1/sessions/{}", on_victim[0])),
        )
        .await;
        if s["sequence"].as_u64().unwrap_or(0) >= 60 {
            break;
        }
        assert!(Instant::now() < deadline, "streaming did not start: {s}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let mut before = Vec::new();
    for name in &on_victim {
        let (_, s) = get(&c, &fleet.instance(0).url(&format!("/v1/sessions/{name}"))).await;
        before.push(s["sequence"].as_u64().unwrap());
    }
    fleet.kill(victim);
    let killed = Instant::now();
    // Its sessions answer again, from the survivors, within 5 s.
    let survivors_before: Vec<BTreeSet<String>> = vec![
        local_sessions(&c, &fleet, 0).await,
        local_sessions(&c, &fleet, 1).await,
    ];
    let mut worst = Duration::ZERO;
    for (name, acked_before) in on_victim.iter().zip(&before) {
        let url = fleet.instance(0).url(&format!("/v1/sessions/{name}"));
        loop {
            let answer = c.get(&url).send().await;
            if let Ok(a) = answer {
                if a.status().as_u16() == 200 {
                    let s: Value = a.json().await.unwrap();
                    if s["recovering"] == false {
                        // Everything acknowledged before the kill is there.
                        assert!(s["sequence"].as_u64().unwrap() >= *acked_before, "{s}");
                        break;
                    }
                }
            }
            assert!(
                killed.elapsed() < Duration::from_secs(5),
                "{name} not adopted within 5 s\n{}",
                fleet.logs()
            );
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        worst = worst.max(killed.elapsed());
    }
    eprintln!(
        "adopted {} sessions within {:.0} ms of the kill",
        on_victim.len(),
        worst.as_secs_f64() * 1e3
    );
    // They went to the survivors by placement; the survivors' own sessions stayed put.
    for name in &on_victim {
        let owner = fleet.owner(name);
        assert!(local_sessions(&c, &fleet, owner).await.contains(name));
    }
    for (i, held) in survivors_before.iter().enumerate() {
        let now = local_sessions(&c, &fleet, i).await;
        assert!(held.is_subset(&now), "{}: {held:?} -> {now:?}", fleet.id(i));
    }
    // Every stream completes; each batch applied once.
    for (name, task) in streams {
        let applied = task.await.unwrap();
        let (_, s) = get(&c, &fleet.instance(1).url(&format!("/v1/sessions/{name}"))).await;
        assert_eq!(
            s["sequence"].as_u64().unwrap() as usize,
            per_session,
            "{name}: {s}"
        );
        assert_eq!(
            s["num_variables"].as_u64().unwrap() as usize,
            per_session,
            "{name}: {s}"
        );
        assert!(applied <= per_session);
    }
    // The instance comes back: the survivors release its sessions to it (a join moves them).
    fleet.start_instance(victim);
    fleet.wait_settled(&z).await;
    let back = Instant::now();
    for name in &on_victim {
        // Listed by its owner again, and done replaying its journal there (a session answers
        // reads while it recovers, saying so).
        let s = loop {
            if local_sessions(&c, &fleet, victim).await.contains(name) {
                let (_, s) = get(&c, &fleet.instance(0).url(&format!("/v1/sessions/{name}"))).await;
                if s["recovering"] == false {
                    break s;
                }
            }
            assert!(
                back.elapsed() < Duration::from_secs(10),
                "{name} not handed back\n{}",
                fleet.logs()
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        assert_eq!(
            s["sequence"].as_u64().unwrap() as usize,
            per_session,
            "{name}: {s}"
        );
        let url = fleet
            .instance(1)
            .url(&format!("/v1/sessions/{name}/batches"));
        let (status, ack) = post(
            &c,
            &url,
            &small_batch(&format!("robot-{name}"), per_session as u64),
        )
        .await;
        assert_eq!(
            (status, ack["duplicate"].clone()),
            (200, json!(true)),
            "{ack}"
        );
    }
    let handed_back = back.elapsed();
    // zenoh follows the moves: a robot's put reaches the session's owner now, and only it.
    let name = &on_victim[0];
    let acks = z
        .declare_subscriber(format!("factord/{name}/out/acks"))
        .await
        .unwrap();
    let errors = z
        .declare_subscriber(format!("factord/{name}/out/errors"))
        .await
        .unwrap();
    let last = per_session as u64;
    let batch = json!({"variables": [{"key": last, "kind": "se2"}],
        "factors": [{"type": "between_se2", "keys": [last - 1, last], "measurement": [1, 0, 0],
                     "sigmas": [0.1, 0.1, 0.05]}],
        "producer": format!("robot-{name}"), "producer_seq": last + 1});
    let deadline = Instant::now() + Duration::from_secs(15);
    loop {
        z.put(format!("factord/{name}/in/batch"), batch.to_string())
            .await
            .unwrap();
        match tokio::time::timeout(Duration::from_millis(500), acks.recv_async()).await {
            Ok(Ok(sample)) => {
                let ack: Value = serde_json::from_slice(&sample.payload().to_bytes()).unwrap();
                assert_eq!(ack["producer_seq"], last + 1, "{ack}");
                break;
            }
            _ => assert!(Instant::now() < deadline, "no ack over zenoh for {name}"),
        }
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    // Repeats of the put (before its ack arrived) are answered as duplicates, by the owner only.
    while let Ok(Some(sample)) = acks.try_recv() {
        let ack: Value = serde_json::from_slice(&sample.payload().to_bytes()).unwrap();
        assert_eq!(ack["duplicate"], true, "{ack}");
    }
    assert!(
        errors.try_recv().unwrap().is_none(),
        "a put reached an instance that does not own {name}"
    );
    let (_, s) = get(&c, &fleet.instance(0).url(&format!("/v1/sessions/{name}"))).await;
    assert_eq!(s["sequence"].as_u64().unwrap(), last + 1, "{s}");
    eprintln!(
        "handed back {} sessions within {:.0} ms of settling",
        on_victim.len(),
        handed_back.as_secs_f64() * 1e3
    );
    for i in 0..3 {
        assert!(
            !fleet.instance(i).stderr().contains("panicked"),
            "{}",
            fleet.logs()
        );
    }
}
