//! The real server over real sockets: HTTP (reqwest) and zenoh (a peer on loopback, scouting off).

use crate::common;

use std::time::{Duration, Instant};

use common::server::{
    client, create, delete_session, g2o_batches, get, post, post_raw, start_long_solve, zenoh_get,
    zenoh_peer, TestServer,
};
use common::{synthetic_helix_3d, synthetic_manhattan};
use serde_json::{json, Value};

async fn batch(
    c: &reqwest::Client,
    s: &TestServer,
    session: &str,
    b: &Value,
    wait: bool,
) -> (u16, Value) {
    let url = s.url(&format!("/v1/sessions/{session}/batches?wait={wait}"));
    post(c, &url, b).await
}

async fn stats(c: &reqwest::Client, s: &TestServer, session: &str) -> Value {
    let (status, v) = get(c, &s.url(&format!("/v1/sessions/{session}"))).await;
    assert_eq!(status, 200, "{v}");
    v
}

async fn estimate(c: &reqwest::Client, s: &TestServer, session: &str) -> Value {
    let (status, v) = get(c, &s.url(&format!("/v1/sessions/{session}/estimate"))).await;
    assert_eq!(status, 200, "{v}");
    v
}

/// chi2 of the batch optimum of a g2o text, solved in-process.
fn batch_optimum(text: &str) -> f64 {
    let mut g = factord::io::parse_text(text, std::path::Path::new("fixture"), None).unwrap();
    factord::solver::optimize(&mut g.problem, &Default::default(), &mut |_| {
        std::ops::ControlFlow::Continue(())
    })
    .unwrap()
    .final_chi2
}

fn assert_close(a: f64, b: f64, rel: f64, what: &str) {
    assert!(
        (a - b).abs() <= rel * b.abs().max(1e-12),
        "{what}: {a} vs {b}"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn curl_style_batch_job() {
    let s = TestServer::start(&[]);
    let c = client();
    let health = get(&c, &s.url("/v1/health")).await;
    assert_eq!(health.0, 200);
    assert_eq!(health.1["status"], "ok");

    let text = synthetic_manhattan(300, 11);
    let (status, v) = post_raw(&c, &s.url("/v1/jobs"), text.clone()).await;
    assert_eq!(status, 200);
    assert_close(
        v["summary"]["final_chi2"].as_f64().unwrap(),
        batch_optimum(&text),
        1e-9,
        "job chi2",
    );
    assert_eq!(v["estimate"]["variables"].as_array().unwrap().len(), 300);

    // The optimised file itself when asked.
    let resp = c
        .post(s.url("/v1/jobs"))
        .header("accept", "text/plain")
        .body(text.clone())
        .send()
        .await
        .unwrap();
    assert!(resp.headers()["content-type"]
        .to_str()
        .unwrap()
        .starts_with("text/plain"));
    let g2o = resp.text().await.unwrap();
    assert_eq!(
        g2o.lines().filter(|l| l.starts_with("VERTEX_SE2")).count(),
        300
    );
    let tum = c
        .post(s.url("/v1/jobs?output=tum&method=lm"))
        .body(text)
        .send()
        .await
        .unwrap();
    let tum = tum.text().await.unwrap();
    // As `solve --tum` and session exports: a header says the first column is the vertex id.
    assert_eq!(
        tum.lines().next(),
        Some(factord::io::tum::VERTEX_ID_HEADER.trim_end()),
        "{tum}"
    );
    assert_eq!(
        tum.lines().filter(|l| !l.starts_with('#')).count(),
        300,
        "{tum}"
    );

    if let Some(intel) = common::data_file("2d/converted/intel_lsslam.g2o") {
        let body = std::fs::read(intel).unwrap();
        let v: Value = c
            .post(s.url("/v1/jobs"))
            .body(body)
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        assert_close(
            v["summary"]["final_chi2"].as_f64().unwrap(),
            65.402048,
            1e-6,
            "intel",
        );
    }
    // Bad jobs.
    for (query, body, field) in [
        ("?format=bal", "x", "body"),
        ("?format=pcd", "x", "format"),
        ("?output=bal", "VERTEX_SE2 0 0 0 0", "output"),
        ("?method=newton", "VERTEX_SE2 0 0 0 0", "method"),
        ("", "VERTEX_SE2 0 0 zero 0", "body"),
        ("?max_iterations=0", "VERTEX_SE2 0 0 0 0", "max_iterations"),
    ] {
        let (status, v) = post_raw(&c, &s.url(&format!("/v1/jobs{query}")), body).await;
        assert_eq!(status, 400, "{query}");
        assert_eq!(v["error"]["field"], field, "{v}");
    }
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn session_fed_over_http_is_read_over_zenoh() {
    let s = TestServer::start(&[]);
    let c = client();
    let text = synthetic_manhattan(250, 5);
    let batches = g2o_batches(&text);
    create(&c, &s, &json!({"session": "walk", "kind": "pose_graph_2d"})).await;

    let z = zenoh_peer(&s.zenoh).await;
    // Collect publications without bounding them (a full FIFO would stall this peer's replies).
    let (pose_tx, poses) = std::sync::mpsc::channel::<Value>();
    let (summary_tx, summaries) = std::sync::mpsc::channel::<Value>();
    let mut subscribers = Vec::new();
    for (key, tx) in [
        ("factord/walk/out/poses", pose_tx),
        ("factord/walk/out/summary", summary_tx),
    ] {
        let tx = std::sync::Mutex::new(tx);
        subscribers.push(
            z.declare_subscriber(key)
                .callback(move |sample| {
                    let v = serde_json::from_slice(&sample.payload().to_bytes()).unwrap();
                    let _ = tx.lock().unwrap().send(v);
                })
                .await
                .unwrap(),
        );
    }
    // Wait until the server's zenoh peer has our subscriptions (its queryable answers first).
    zenoh_get(&z, "factord/walk/estimate", None).await.unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;

    let n = batches.len();
    for (i, b) in batches.iter().enumerate() {
        let (status, ack) = batch(&c, &s, "walk", b, i + 1 == n).await;
        assert_eq!(status, 200, "{ack}");
        assert_eq!(ack["sequence"], i as u64 + 1);
    }
    let over_http = estimate(&c, &s, "walk").await;
    let over_zenoh = zenoh_get(&z, "factord/walk/estimate", None).await.unwrap();
    assert_eq!(over_http["variables"], over_zenoh["variables"]);
    assert_eq!(over_zenoh["variables"].as_array().unwrap().len(), 250);
    assert_eq!(over_zenoh["sequence"], n as u64);

    // Range and "changed since" reads over zenoh.
    let range = zenoh_get(&z, "factord/walk/estimate?from=10;to=19", None)
        .await
        .unwrap();
    assert_eq!(range["variables"].as_array().unwrap().len(), 10);
    let latest = zenoh_get(&z, &format!("factord/walk/estimate?since={n}"), None)
        .await
        .unwrap();
    assert!(latest["variables"].as_array().unwrap().is_empty());
    let bad = zenoh_get(&z, "factord/walk/estimate?since=-1", None)
        .await
        .unwrap_err();
    assert_eq!(bad["error"]["field"], "since");

    // The incremental session reaches the batch optimum once idle: the last update alone ends
    // up to ~1e-4 from it (the request path's relinearisation threshold), the polish that
    // follows closes the rest, so wait for it (under load it may not have run yet).
    let mut st = stats(&c, &s, "walk").await;
    for _ in 0..200 {
        if st["converged"] == true {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
        st = stats(&c, &s, "walk").await;
    }
    assert_eq!(st["converged"], true, "the idle session polished: {st}");
    assert_close(
        st["chi2"].as_f64().unwrap(),
        batch_optimum(&text),
        1e-5,
        "incremental chi2 once idle",
    );
    // Streams: changed poses and summaries were published with the sequence they reflect.
    let mut last_pose_sequence = 0;
    tokio::time::sleep(Duration::from_millis(200)).await;
    while let Ok(v) = poses.try_recv() {
        assert_eq!(v["type"], "estimate");
        last_pose_sequence = last_pose_sequence.max(v["sequence"].as_u64().unwrap());
    }
    assert_eq!(last_pose_sequence, n as u64);
    let v = summaries.try_recv().expect("a summary was published");
    assert!(v["summary"]["final_chi2"].is_number());

    // A pose appended to the idle, converged session with only its odometry, guessed from that
    // odometry, adds no chi2: it skips solving. (While streaming, whether a batch finds the
    // session idle depends on the machine's load, so the skip is checked here.)
    let skipped = st["skipped_solves"].as_u64().unwrap();
    let info = [400.0, 0.0, 0.0, 400.0, 0.0, 10000.0];
    let odometry = json!({
        "variables": [{"key": 250, "kind": "se2"}],
        "factors": [{"type": "between_se2", "keys": [249, 250],
                     "measurement": [1.0, 0.0, 0.0], "information": info}],
    });
    let (status, ack) = batch(&c, &s, "walk", &odometry, true).await;
    assert_eq!(status, 200, "{ack}");
    let st = stats(&c, &s, "walk").await;
    assert_eq!(
        st["skipped_solves"].as_u64().unwrap(),
        skipped + 1,
        "an odometry-only update skips solving: {st}"
    );
    assert_eq!(st["converged"], true, "{st}");
    drop(subscribers);
    z.close().await.unwrap();
    s.assert_no_panic();
}

/// Reads SSE events from `resp` until `stop` says so; returns them as (event, data).
async fn read_sse(
    resp: &mut reqwest::Response,
    deadline: Duration,
    mut stop: impl FnMut(&str, &Value) -> bool,
) -> Vec<(String, Value)> {
    let end = Instant::now() + deadline;
    let mut buffer = String::new();
    let mut events = Vec::new();
    while Instant::now() < end {
        let chunk = tokio::time::timeout(end - Instant::now(), resp.chunk()).await;
        let Ok(Ok(Some(bytes))) = chunk else { break };
        buffer.push_str(&String::from_utf8_lossy(&bytes));
        while let Some(pos) = buffer.find("\n\n") {
            let block: String = buffer.drain(..pos + 2).collect();
            let mut name = String::new();
            let mut data = String::new();
            for line in block.lines() {
                if let Some(v) = line.strip_prefix("event:") {
                    name = v.trim().into();
                } else if let Some(v) = line.strip_prefix("data:") {
                    data.push_str(v.trim());
                }
            }
            if data.is_empty() {
                continue;
            }
            let value: Value = serde_json::from_str(&data).unwrap_or(Value::String(data));
            let done = stop(&name, &value);
            events.push((name, value));
            if done {
                return events;
            }
        }
    }
    events
}

#[tokio::test(flavor = "multi_thread")]
async fn session_fed_over_zenoh_is_read_over_sse() {
    let s = TestServer::start(&[]);
    let c = client();
    let z = zenoh_peer(&s.zenoh).await;
    let created = zenoh_get(
        &z,
        "factord/rpc",
        Some(&json!({"op": "create_session", "session": "robot", "kind": "pose_graph_3d"})),
    )
    .await
    .unwrap();
    assert_eq!(created["kind"], "pose_graph_3d");
    // Errors come back as error replies naming the problem.
    let dup = zenoh_get(
        &z,
        "factord/rpc",
        Some(&json!({"op": "create_session", "session": "robot", "kind": "pose_graph_3d"})),
    )
    .await
    .unwrap_err();
    assert_eq!(dup["error"]["code"], "session_exists");
    assert_eq!(dup["error"]["status"], 409);

    let mut sse = c
        .get(s.url("/v1/sessions/robot/events"))
        .send()
        .await
        .unwrap();
    assert_eq!(sse.status(), 200);
    let text = synthetic_helix_3d(120, 3);
    let batches = g2o_batches(&text);
    let n = batches.len() as u64;
    let publisher = z.declare_publisher("factord/robot/in/batch").await.unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    for b in &batches {
        publisher.put(b.to_string()).await.unwrap();
    }
    // A bad batch over zenoh: rejected on the session's error stream, nothing applied.
    publisher
        .put(json!({"factors": [{"type": "between_se3", "keys": [0, 999999], "measurement": [0,0,0,0,0,0,1], "sigmas": [1,1,1,1,1,1]}]}).to_string())
        .await
        .unwrap();
    // Solves run asynchronously: read until the rejection and some solver iterations arrived.
    let (mut saw_error, mut saw_stats) = (false, false);
    let events = read_sse(&mut sse, Duration::from_secs(60), |name, _| {
        saw_error |= name == "errors";
        saw_stats |= name == "stats";
        saw_error && saw_stats
    })
    .await;
    let names: Vec<&str> = events.iter().map(|(n, _)| n.as_str()).collect();
    assert!(
        names.contains(&"acks") && names.contains(&"poses") && names.contains(&"stats"),
        "{names:?}"
    );
    let error = &events.iter().find(|(n, _)| n == "errors").unwrap().1;
    assert_eq!(error["error"]["code"], "unknown_variable", "{error}");
    assert_eq!(error["error"]["field"], "factors[0].keys[1]");
    let acked: Vec<u64> = events
        .iter()
        .filter(|(n, _)| n == "acks")
        .map(|(_, v)| v["sequence"].as_u64().unwrap())
        .collect();
    assert_eq!(
        acked,
        (1..=n).collect::<Vec<_>>(),
        "every batch acknowledged in order"
    );

    // Solve to the end and compare with the batch optimum.
    let done = zenoh_get(
        &z,
        "factord/rpc",
        Some(&json!({"op": "optimize", "session": "robot", "wait": true})),
    )
    .await
    .unwrap();
    assert_eq!(done["stats"]["sequence"], n);
    assert_eq!(done["stats"]["num_variables"], 120);
    assert_close(
        done["stats"]["chi2"].as_f64().unwrap(),
        batch_optimum(&text),
        1e-4,
        "3D chi2",
    );
    z.close().await.unwrap();
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn twenty_sessions_in_parallel() {
    let s = std::sync::Arc::new(TestServer::start(&[]));
    let mut tasks = Vec::new();
    for i in 0..20u64 {
        let s = std::sync::Arc::clone(&s);
        tasks.push(tokio::spawn(async move {
            let c = client();
            let name = format!("p{i}");
            let (kind, text, policy) = match i % 4 {
                0 => ("pose_graph_2d", synthetic_manhattan(150, i), json!({"policy": "every_batch"})),
                1 => ("pose_graph_2d", synthetic_manhattan(400, i), json!({"policy": "every_n_factors", "factors": 40})),
                2 => ("pose_graph_3d", synthetic_helix_3d(80, i), json!({"policy": "every_ms", "milliseconds": 20})),
                _ => ("pose_graph_2d", synthetic_manhattan(200, i), json!({"policy": "manual"})),
            };
            create(&c, &s, &json!({"session": name, "kind": kind, "auto_optimize": policy})).await;
            let batches = g2o_batches(&text);
            for (k, b) in batches.iter().enumerate() {
                let (status, v) = batch(&c, &s, &name, b, false).await;
                assert_eq!(status, 200, "{name}: {v}");
                if k % 25 == 0 {
                    // Interleaved bad batches change nothing (solves may finish meanwhile, so
                    // compare what only batches change).
                    let before = stats(&c, &s, &name).await;
                    let bad = json!({"variables": [{"key": 1_000_000, "kind": "se2", "value": [0, 0, 0]}],
                                     "factors": [{"type": "between_se2", "keys": [1_000_000, 1_000_001], "measurement": [1,0,0], "sigmas": [1,1,1]}]});
                    let (status, _) = batch(&c, &s, &name, &bad, false).await;
                    assert!(status == 400 || status == 422);
                    let after = stats(&c, &s, &name).await;
                    for field in ["sequence", "num_variables", "num_factors"] {
                        assert_eq!(after[field], before[field], "{name}: {field}");
                    }
                    let (status, range) = get(&c, &s.url(&format!("/v1/sessions/{name}/estimate?from=1000000"))).await;
                    assert_eq!((status, range["variables"].as_array().unwrap().len()), (200, 0));
                }
            }
            let (status, done) = post(&c, &s.url(&format!("/v1/sessions/{name}/optimize?wait=true")), &json!({})).await;
            assert_eq!(status, 200, "{done}");
            let st = &done["stats"];
            assert_eq!(st["sequence"].as_u64().unwrap(), batches.len() as u64);
            assert_eq!(st["solved_sequence"], st["sequence"]);
            assert!(st["converged"].as_bool().unwrap(), "{name}: {st}");
            assert_close(st["chi2"].as_f64().unwrap(), batch_optimum(&text), 1e-4, &name);
        }));
    }
    for t in tasks {
        t.await.expect("session task");
    }
    let c = client();
    let (_, list) = get(&c, &s.url("/v1/sessions")).await;
    assert_eq!(list["sessions"].as_array().unwrap().len(), 20);
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn cancel_and_delete_during_a_solve() {
    let s = TestServer::start(&[]);
    let c = client();
    start_long_solve(&c, &s, "long").await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let (status, v) = post(&c, &s.url("/v1/sessions/long/cancel"), &json!({})).await;
    assert_eq!((status, v["cancelled"].as_bool()), (200, Some(true)), "{v}");
    let deadline = Instant::now() + Duration::from_secs(5);
    let st = loop {
        let st = stats(&c, &s, "long").await;
        if !st["solving"].as_bool().unwrap() {
            break st;
        }
        assert!(Instant::now() < deadline, "cancel did not stop the solve");
        tokio::time::sleep(Duration::from_millis(10)).await;
    };
    assert_eq!(st["last_summary"]["termination"]["reason"], "interrupted");
    assert!(st["last_summary"]["iterations"].as_u64().unwrap() >= 1);
    // The estimate is the last accepted iterate: finite, every pose there.
    assert_eq!(
        estimate(&c, &s, "long").await["variables"]
            .as_array()
            .unwrap()
            .len(),
        1500
    );

    // Delete while solving: the session is gone at once, the worker is freed for others.
    let (status, _) = post(&c, &s.url("/v1/sessions/long/optimize"), &json!({})).await;
    assert_eq!(status, 202);
    tokio::time::sleep(Duration::from_millis(200)).await;
    let (status, v) = delete_session(&c, &s, "long").await;
    assert_eq!((status, &v["deleted"]), (200, &json!("long")));
    let (status, v) = get(&c, &s.url("/v1/sessions/long")).await;
    assert_eq!(
        (status, v["error"]["code"].as_str()),
        (404, Some("unknown_session"))
    );
    create(
        &c,
        &s,
        &json!({"session": "after", "kind": "pose_graph_2d"}),
    )
    .await;
    let text = synthetic_manhattan(50, 1);
    for b in g2o_batches(&text) {
        let (status, v) = batch(&c, &s, "after", &b, true).await;
        assert_eq!(status, 200, "{v}");
        assert_eq!(v["solved"], true);
    }
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn back_pressure_answers_429_and_503_with_retry_after() {
    let config = common::temp_dir("config").join("factord.json");
    std::fs::write(
        &config,
        json!({"limits": {"workers": 1, "max_pending_factors": 30, "max_jobs": 1}}).to_string(),
    )
    .unwrap();
    let s = TestServer::start(&["--config", config.to_str().unwrap()]);
    let c = client();
    assert_eq!(get(&c, &s.url("/v1/health")).await.1["workers"], 1);
    start_long_solve(&c, &s, "busy").await;

    // Batches during the solve are accepted and queued until the pending limit, then 429.
    let mut statuses = Vec::new();
    for next_key in 5000u64..5010 {
        let factors: Vec<Value> = (0..10)
            .map(|_| json!({"type": "between_se2", "keys": [0, 1], "measurement": [1, 0, 0], "sigmas": [1, 1, 1]}))
            .collect();
        let b = json!({"variables": [{"key": next_key, "kind": "se2", "value": [0, 0, 0]}], "factors": factors});
        let resp = c
            .post(s.url("/v1/sessions/busy/batches"))
            .header("content-type", "application/json")
            .body(b.to_string())
            .send()
            .await
            .unwrap();
        statuses.push(resp.status().as_u16());
        if resp.status() == 429 {
            assert_eq!(resp.headers()["retry-after"], "1");
            let v: Value = resp.json().await.unwrap();
            assert_eq!(v["error"]["code"], "too_many_pending");
        }
    }
    assert_eq!(statuses[..3], [200, 200, 200], "{statuses:?}");
    assert!(statuses[3..].iter().all(|s| *s == 429), "{statuses:?}");
    assert_eq!(stats(&c, &s, "busy").await["pending_batches"], 3);

    // Cancelling the long solve frees the worker: the pending batches are applied and solved.
    post(&c, &s.url("/v1/sessions/busy/cancel"), &json!({})).await;
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let st = stats(&c, &s, "busy").await;
        if st["pending_batches"] == 0 && st["num_variables"] == 1503 {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "pending batches were not applied: {st}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }

    // Jobs: one long job runs, the next is turned away while max_jobs (1) are in flight.
    let endless_job = "?max_iterations=100000&function_tolerance=0&gradient_tolerance=0&parameter_tolerance=0&init=none";
    let running = {
        let c = c.clone();
        let url = s.url(&format!("/v1/jobs{endless_job}"));
        tokio::spawn(async move {
            c.post(url)
                .body(synthetic_manhattan(1500, 4))
                .send()
                .await
                .map(|r| r.status())
        })
    };
    tokio::time::sleep(Duration::from_millis(500)).await;
    let resp = c
        .post(s.url("/v1/jobs"))
        .body(synthetic_manhattan(20, 2))
        .send()
        .await
        .unwrap();
    assert_eq!(resp.status(), 503);
    assert_eq!(resp.headers()["retry-after"], "1");
    let v: Value = resp.json().await.unwrap();
    assert_eq!(v["error"]["code"], "too_many_jobs");
    // Fairness: the long job yields its only worker to a small session every time slice.
    create(
        &c,
        &s,
        &json!({"session": "small", "kind": "pose_graph_2d"}),
    )
    .await;
    let started = Instant::now();
    for b in g2o_batches(&synthetic_manhattan(30, 9)) {
        let (status, v) = batch(&c, &s, "small", &b, true).await;
        assert_eq!((status, &v["solved"]), (200, &json!(true)), "{v}");
    }
    assert!(
        started.elapsed() < Duration::from_secs(30),
        "small session starved"
    );
    assert!(!running.is_finished(), "the long job is still running");
    running.abort();
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn bad_input_gets_4xx_naming_the_problem_and_changes_nothing() {
    let s = TestServer::start(&["--max-body-bytes", "100000"]);
    let c = client();
    create(&c, &s, &json!({"session": "g", "kind": "pose_graph_2d"})).await;
    let good = json!({"variables": [{"key": 1, "kind": "se2", "value": [0, 0, 0]},
                                    {"key": 2, "kind": "se2", "value": [1, 0, 0]}],
                      "factors": [{"type": "between_se2", "keys": [1, 2], "measurement": [1, 0, 0], "sigmas": [0.1, 0.1, 0.1]}]});
    assert_eq!(batch(&c, &s, "g", &good, true).await.0, 200);
    let before_estimate = estimate(&c, &s, "g").await;
    let before_stats = stats(&c, &s, "g").await;

    let factor = |keys: Value, z: Value, info: Value| json!({"type": "between_se2", "keys": keys, "measurement": z, "information": info});
    let id = json!([100, 0, 0, 100, 0, 100]);
    let cases: Vec<(&str, Value, u16, &str, Option<&str>)> = vec![
        (
            "unknown key",
            json!({"factors": [factor(json!([1, 7]), json!([1, 0, 0]), id.clone())]}),
            422,
            "unknown_variable",
            Some("factors[0].keys[1]"),
        ),
        (
            "duplicate key",
            json!({"variables": [{"key": 2, "kind": "se2", "value": [0, 0, 0]}]}),
            422,
            "duplicate_variable",
            Some("variables[0].key"),
        ),
        (
            "duplicate within batch",
            json!({"variables": [{"key": 5, "kind": "se2", "value": [0, 0, 0]}, {"key": 5, "kind": "se2", "value": [0, 0, 0]}]}),
            422,
            "duplicate_variable",
            Some("variables[1].key"),
        ),
        (
            "wrong value dimension",
            json!({"variables": [{"key": 3, "kind": "se2", "value": [0, 0]}]}),
            400,
            "wrong_dimension",
            Some("variables[0].value"),
        ),
        (
            "wrong measurement dimension",
            json!({"factors": [factor(json!([1, 2]), json!([1, 0, 0, 0]), id.clone())]}),
            400,
            "wrong_dimension",
            Some("factors[0].measurement"),
        ),
        (
            "wrong information size",
            json!({"factors": [factor(json!([1, 2]), json!([1, 0, 0]), json!([1, 2, 3, 4]))]}),
            400,
            "wrong_dimension",
            Some("factors[0].information"),
        ),
        (
            "non-PD information",
            json!({"factors": [factor(json!([1, 2]), json!([1, 0, 0]), json!([1, 0, 0, -1, 0, 1]))]}),
            400,
            "bad_information",
            Some("factors[0].information"),
        ),
        (
            "wrong variable kind",
            json!({"variables": [{"key": 3, "kind": "se3", "value": [0, 0, 0, 0, 0, 0, 1]}]}),
            400,
            "wrong_kind",
            Some("variables[0].kind"),
        ),
        (
            "factor of another kind",
            json!({"factors": [{"type": "between_se3", "keys": [1, 2], "measurement": [0, 0, 0, 0, 0, 0, 1], "sigmas": [1, 1, 1, 1, 1, 1]}]}),
            400,
            "unknown_factor_type",
            Some("factors[0].type"),
        ),
        (
            "one bad element of many",
            json!({"variables": [{"key": 3, "kind": "se2", "value": [0, 0, 0]}],
            "factors": [factor(json!([2, 3]), json!([1, 0, 0]), id.clone()), factor(json!([3, 9]), json!([1, 0, 0]), id.clone())]}),
            422,
            "unknown_variable",
            Some("factors[1].keys[1]"),
        ),
        (
            "missing guess",
            json!({"variables": [{"key": 3, "kind": "se2"}]}),
            422,
            "missing_value",
            Some("variables[0].value"),
        ),
        (
            "unknown factor to remove",
            json!({"remove_factors": [42]}),
            422,
            "unknown_factor",
            Some("remove_factors[0]"),
        ),
        (
            "fix unknown variable",
            json!({"fix": [77]}),
            422,
            "unknown_variable",
            Some("fix[0]"),
        ),
        (
            "unknown field",
            json!({"factorz": []}),
            400,
            "invalid_field",
            None,
        ),
        (
            "zero sigma",
            json!({"factors": [{"type": "between_se2", "keys": [1, 2], "measurement": [1, 0, 0], "sigmas": [1, 0, 1]}]}),
            400,
            "bad_information",
            Some("factors[0].sigmas[1]"),
        ),
    ];
    for (what, body, status, code, field) in cases {
        let (got, v) = batch(&c, &s, "g", &body, false).await;
        assert_eq!(got, status, "{what}: {v}");
        assert_eq!(v["error"]["code"], code, "{what}: {v}");
        if let Some(field) = field {
            assert_eq!(v["error"]["field"], field, "{what}: {v}");
        }
        assert!(v["error"]["message"]
            .as_str()
            .is_some_and(|m| !m.is_empty()));
    }
    // NaN is not JSON: malformed.
    let (status, v) = post_raw(
        &c,
        &s.url("/v1/sessions/g/batches"),
        r#"{"variables": [{"key": 3, "kind": "se2", "value": [NaN, 0, 0]}]}"#,
    )
    .await;
    assert_eq!(status, 400);
    assert_eq!(v["error"]["code"], "malformed_json");
    let (status, v) = post_raw(
        &c,
        &s.url("/v1/sessions/g/batches"),
        r#"{"variables": [{"key": 3, "kind": "se2", "value": [0, 1e400, 0]}]}"#,
    )
    .await;
    assert_eq!(status, 400, "infinite number");
    assert!(
        v["error"]["message"]
            .as_str()
            .unwrap()
            .contains("out of range"),
        "{v}"
    );
    let resp = c
        .post(s.url("/v1/sessions/g/batches"))
        .header("content-type", "application/json")
        .body("{\"variables\": [")
        .send()
        .await
        .unwrap();
    assert_eq!(resp.status(), 400);
    // Unknown session, unknown route.
    let (status, v) = batch(&c, &s, "nope", &good, false).await;
    assert_eq!(
        (status, v["error"]["code"].as_str()),
        (404, Some("unknown_session"))
    );
    let (status, v) = get(&c, &s.url("/v2/anything")).await;
    assert_eq!(
        (status, v["error"]["code"].as_str()),
        (404, Some("no_route"))
    );
    // Oversize body.
    let big = json!({"variables": (0..5000).map(|k| json!({"key": 100 + k, "kind": "se2", "value": [0, 0, 0]})).collect::<Vec<_>>()});
    // The server answers 413 as soon as the limit is crossed and closes the connection; a client
    // still writing the body may see the reset instead of the answer, so try a few times.
    // A client of its own: the server closes that connection, which must not be reused.
    let once = client();
    let mut answer = None;
    for _ in 0..10 {
        let sent = once
            .post(s.url("/v1/sessions/g/batches"))
            .header("content-type", "application/json")
            .body(big.to_string())
            .send()
            .await;
        if let Ok(resp) = sent {
            let status = resp.status().as_u16();
            answer = Some((status, resp.json::<Value>().await.unwrap()));
            break;
        }
    }
    let (status, v) = answer.expect("an answer to the oversize body");
    assert_eq!(
        (status, v["error"]["code"].as_str()),
        (413, Some("body_too_large")),
        "{v}"
    );
    // Bad session requests.
    let (status, v) = post(&c, &s.url("/v1/sessions"), &json!({"kind": "no_such_kind"})).await;
    assert_eq!((status, v["error"]["field"].as_str()), (400, Some("kind")));
    let (status, v) = post(
        &c,
        &s.url("/v1/sessions"),
        &json!({"kind": "pose_graph_2d", "session": "a/b"}),
    )
    .await;
    assert_eq!(
        (status, v["error"]["field"].as_str()),
        (400, Some("session"))
    );
    let (status, v) = post(
        &c,
        &s.url("/v1/sessions"),
        &json!({"kind": "pose_graph_2d", "options": {"max_iterations": 0}}),
    )
    .await;
    assert_eq!(
        (status, v["error"]["field"].as_str()),
        (400, Some("options.max_iterations"))
    );
    let (status, v) = get(&c, &s.url("/v1/sessions/g/estimate?since=x")).await;
    assert_eq!(
        (status, v["error"]["code"].as_str()),
        (400, Some("invalid_query"))
    );

    // Nothing of it was applied.
    assert_eq!(estimate(&c, &s, "g").await, before_estimate);
    let after = stats(&c, &s, "g").await;
    for field in ["sequence", "num_variables", "num_factors", "chi2"] {
        assert_eq!(after[field], before_stats[field], "{field}");
    }
    // And the session still works.
    let more = json!({"variables": [{"key": 3, "kind": "se2"}], "factors": [factor(json!([2, 3]), json!([1, 0, 0]), id)]});
    let (status, v) = batch(&c, &s, "g", &more, true).await;
    assert_eq!((status, v["predicted"].clone()), (200, json!([3])), "{v}");
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn removals_fixes_and_guesses_are_applied_atomically() {
    let s = TestServer::start(&["--no-zenoh"]);
    let c = client();
    create(&c, &s, &json!({"session": "edit", "kind": "pose_graph_2d"})).await;
    let b = json!({"variables": [{"key": 0, "kind": "se2", "value": [0, 0, 0], "fixed": true},
                                 {"key": 1, "kind": "se2"}, {"key": 2, "kind": "se2"}],
                   "factors": [{"type": "between_se2", "keys": [0, 1], "measurement": [1, 0, 0], "sigmas": [0.1, 0.1, 0.1]},
                               {"type": "between_se2", "keys": [1, 2], "measurement": [1, 0, 0], "sigmas": [0.1, 0.1, 0.1]},
                               {"type": "between_se2", "keys": [0, 2], "measurement": [3, 0, 0], "sigmas": [0.1, 0.1, 0.1]}]});
    let (_, ack) = batch(&c, &s, "edit", &b, true).await;
    assert_eq!(ack["factor_ids"], json!([0, 1, 2]));
    assert!(
        stats(&c, &s, "edit").await["chi2"].as_f64().unwrap() > 1.0,
        "conflicting loop"
    );
    // Remove the outlier loop closure: the chain is consistent again.
    let (status, _) = batch(&c, &s, "edit", &json!({"remove_factors": [2]}), true).await;
    assert_eq!(status, 200);
    let st = stats(&c, &s, "edit").await;
    assert!(st["chi2"].as_f64().unwrap() < 1e-12, "{st}");
    assert_eq!(st["num_factors"], 2);
    // Removing it twice fails.
    assert_eq!(
        batch(&c, &s, "edit", &json!({"remove_factors": [2]}), false)
            .await
            .0,
        422
    );
    // A new guess for a fixed pose moves it; the solve keeps it there.
    let (status, _) = batch(
        &c,
        &s,
        "edit",
        &json!({"guesses": [{"key": 0, "value": [5, 5, 0]}]}),
        true,
    )
    .await;
    assert_eq!(status, 200);
    let est = estimate(&c, &s, "edit").await;
    assert_eq!(est["variables"][0]["value"], json!([5.0, 5.0, 0.0]));
    let x2 = est["variables"][2]["value"][0].as_f64().unwrap();
    assert!((x2 - 7.0).abs() < 1e-9, "{est}");
    // Reads of what changed since a sequence.
    let (_, since) = get(&c, &s.url("/v1/sessions/edit/estimate?since=3")).await;
    assert_eq!(since["variables"].as_array().unwrap().len(), 0);
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn sigterm_stops_a_running_solve_and_exits_cleanly() {
    let s = TestServer::start(&[]);
    let c = client();
    start_long_solve(&c, &s, "long").await;
    let lock = s.state_dir.join("factord.lock");
    assert!(lock.exists());
    let state_dir = s.state_dir.clone();
    let started = Instant::now();
    let (status, log) = s.terminate(Duration::from_secs(15));
    let status = status.expect("exited after SIGTERM");
    assert!(status.success(), "{status:?}\n{log}");
    assert!(started.elapsed() < Duration::from_secs(10));
    // Released: the lock file stays (removing it would reopen a race), but its lock is free.
    let lock = std::fs::File::open(state_dir.join("factord.lock")).unwrap();
    assert!(lock.try_lock().is_ok(), "state directory released");
    assert!(!log.contains("panicked"), "{log}");
}

#[tokio::test(flavor = "multi_thread")]
async fn configuration_flags_override_environment_override_file() {
    let config = common::temp_dir("config").join("factord.json");
    std::fs::write(&config, json!({"limits": {"workers": 1}}).to_string()).unwrap();
    let cfg = config.to_str().unwrap();
    let c = client();
    let s = TestServer::start(&["--config", cfg, "--no-zenoh"]);
    assert_eq!(get(&c, &s.url("/v1/health")).await.1["workers"], 1);
    drop(s);
    let s = TestServer::start_with_env(
        &["--config", cfg, "--no-zenoh"],
        &[("FACTORD_WORKERS", "3")],
    );
    assert_eq!(get(&c, &s.url("/v1/health")).await.1["workers"], 3);
    drop(s);
    let s = TestServer::start_with_env(
        &["--config", cfg, "--no-zenoh", "--workers", "2"],
        &[("FACTORD_WORKERS", "3")],
    );
    assert_eq!(get(&c, &s.url("/v1/health")).await.1["workers"], 2);
    // A broken config file is a clear startup error.
    std::fs::write(&config, r#"{"limits": {"workerz": 1}}"#).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_factord"))
        .args(["serve", "--config", cfg])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("limits.workerz"), "{err}");
}

#[tokio::test(flavor = "multi_thread")]
async fn optimize_requests_run_whatever_the_policy() {
    let s = TestServer::start(&["--no-zenoh"]);
    let c = client();
    for (name, policy) in [
        ("manual", json!({"policy": "manual"})),
        (
            "every-n",
            json!({"policy": "every_n_factors", "factors": 1000000}),
        ),
    ] {
        create(
            &c,
            &s,
            &json!({"session": name, "kind": "pose_graph_2d", "auto_optimize": policy}),
        )
        .await;
        for b in g2o_batches(&synthetic_manhattan(300, 8)) {
            let (status, v) = batch(&c, &s, name, &b, true).await;
            assert_eq!(
                (status, &v["solved"]),
                (200, &json!(false)),
                "no solve is due: {v}"
            );
        }
        // Several concurrent requests: each answers after a solve that started after it.
        let url = s.url(&format!("/v1/sessions/{name}/optimize?wait=true"));
        let requests: Vec<_> = (0..4)
            .map(|_| {
                let (c, url) = (c.clone(), url.clone());
                tokio::spawn(async move { post(&c, &url, &json!({})).await })
            })
            .collect();
        for r in requests {
            let (status, v) = tokio::time::timeout(Duration::from_secs(30), r)
                .await
                .expect("answered")
                .unwrap();
            assert_eq!(status, 200, "{v}");
            assert!(v["stats"]["solves"].as_u64().unwrap() >= 1);
            assert_eq!(v["stats"]["solved_sequence"], 300, "{v}");
        }
    }
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn websocket_carries_batches_in_and_events_out() {
    use futures_util::{SinkExt, StreamExt};
    use tokio_tungstenite::tungstenite::Message;
    let s = TestServer::start(&["--no-zenoh"]);
    let c = client();
    create(&c, &s, &json!({"session": "ws", "kind": "pose_graph_2d"})).await;
    let url = s.url("/v1/sessions/ws/ws").replace("http://", "ws://");
    let (mut socket, _) = tokio_tungstenite::connect_async(&url)
        .await
        .expect("upgrade");
    let text = synthetic_manhattan(60, 13);
    let batches = g2o_batches(&text);
    for b in &batches {
        socket.send(Message::text(b.to_string())).await.unwrap();
    }
    socket
        .send(Message::text(
            json!({"variables": [{"key": 7, "kind": "se2", "value": [0, 0, 0]}]}).to_string(),
        ))
        .await
        .unwrap();
    let (mut acked, mut summaries, mut rejected) = (0, 0, None);
    // Solves run asynchronously: read until the rejection and a summary arrived.
    while rejected.is_none() || summaries == 0 {
        let message = tokio::time::timeout(Duration::from_secs(30), socket.next())
            .await
            .expect("events keep coming")
            .expect("open")
            .unwrap();
        let Message::Text(text) = message else {
            continue;
        };
        let v: Value = serde_json::from_str(&text).unwrap();
        match v["type"].as_str().unwrap() {
            "ack" => acked += 1,
            "summary" => summaries += 1,
            "error" => rejected = Some(v),
            _ => {}
        }
    }
    assert_eq!(acked, batches.len());
    assert!(summaries > 0);
    let rejected = rejected.unwrap();
    assert_eq!(
        rejected["error"]["code"], "duplicate_variable",
        "{rejected}"
    );
    assert_eq!(stats(&c, &s, "ws").await["sequence"], batches.len() as u64);
    // Unknown session: no upgrade.
    let bad = s.url("/v1/sessions/nope/ws").replace("http://", "ws://");
    assert!(tokio_tungstenite::connect_async(&bad).await.is_err());
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn bundle_adjustment_as_a_job_and_as_a_session() {
    let Some(path) = common::data_file("bal/problem-49-7776-pre.txt") else {
        return;
    };
    let s = TestServer::start(&["--no-zenoh"]);
    let c = client();
    let text = std::fs::read_to_string(&path).unwrap();
    // A BAL batch job: LM by default (the gauge is free), Ceres' optimum.
    let (status, v) = post_raw(&c, &s.url("/v1/jobs?format=bal"), text.clone()).await;
    assert_eq!(status, 200);
    let cost = v["summary"]["final_chi2"].as_f64().unwrap() / 2.0;
    assert!((cost - 13344.32).abs() < 1e-3 * 13344.32, "{cost}");
    assert_eq!(v["summary"]["method"], "levenberg_marquardt");
    assert_eq!(
        v["estimate"]["variables"].as_array().unwrap().len(),
        49 + 7776
    );
    assert_eq!(v["estimate"]["variables"][0]["kind"], "snavely_camera");
    let resp = c
        .post(s.url("/v1/jobs?format=bal&output=g2o"))
        .body("1 1 1")
        .send()
        .await
        .unwrap();
    assert_eq!(resp.status(), 400);
    let (status, v) = post_raw(&c, &s.url("/v1/jobs?format=bal"), "2 1 1\n0 3 1 2\n").await;
    assert_eq!(status, 400);
    assert_eq!(v["error"]["field"], "body");

    // The same problem streamed into a bundle_adjustment session: cameras and points, then the
    // observations in a few batches; the session solves with LM and reaches the same optimum.
    let (variables, factor_batches) = common::bal_session::batches(&text, 10_000);
    create(&c, &s, &json!({"session": "ba", "kind": "bundle_adjustment", "auto_optimize": {"policy": "manual"}})).await;
    let (status, v) = batch(&c, &s, "ba", &variables, false).await;
    assert_eq!(status, 200, "{v}");
    for factors in &factor_batches {
        let (status, v) = batch(&c, &s, "ba", factors, false).await;
        assert_eq!(status, 200, "{v}");
    }
    let (status, done) = post(&c, &s.url("/v1/sessions/ba/optimize?wait=true"), &json!({})).await;
    assert_eq!(status, 200, "{done}");
    let st = &done["stats"];
    assert_eq!(
        st["options"]["method"], "levenberg_marquardt",
        "kind default"
    );
    assert!(st["converged"].as_bool().unwrap(), "{st}");
    let cost = st["chi2"].as_f64().unwrap() / 2.0;
    assert!((cost - 13344.32).abs() < 1e-3 * 13344.32, "{cost}");
    // A pose-graph variable does not belong in a BA session.
    let (status, v) = batch(
        &c,
        &s,
        "ba",
        &json!({"variables": [{"key": 999999, "kind": "se2", "value": [0, 0, 0]}]}),
        false,
    )
    .await;
    assert_eq!(
        (status, v["error"]["code"].as_str()),
        (400, Some("wrong_kind"))
    );
    s.assert_no_panic();
}
