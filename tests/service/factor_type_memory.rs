//! User-defined factor types and memory (issue 52, item 4): a session's `memory_bytes` counts
//! its compiled types, sessions declaring identical definitions share one compiled copy (the
//! server compiles it once), a session's and the server's type memory are bounded with 413s
//! naming `factor_types`, and a restart with sessions of large types answers HTTP at once while
//! their types compile in the background. Real `factord serve` processes, real sockets.

use crate::common;

use std::time::{Duration, Instant};

use common::server::{client, get, post, start_with_limits, TestServer};
use serde_json::{json, Value};

/// Leaves of the largest definitions: each adds 2 × 256 tape slots (a scaled copy of the
/// 256-vector parameter and a sum), so 188 of them make ~98 000 slots × 4 derivative lanes,
/// just under `MAX_COST` — about 4 MB compiled, a tenth of a second to compile.
const LEAVES: usize = 188;

/// A definition near the size bounds, unique to `name` and `seed` (its constants).
fn heavy(name: &str, seed: usize) -> Value {
    let x = json!({"mul": [{"at": [{"translation": ["a"]}, 0]}, "m"]});
    let mut terms: Vec<Value> = (0..LEAVES)
        .map(|k| json!({"mul": [1.0 + 0.001 * k as f64 + 1e-7 * seed as f64, x]}))
        .collect();
    while terms.len() > 1 {
        terms = terms
            .chunks(2)
            .map(|pair| match pair {
                [a, b] => json!({"add": [a, b]}),
                [a] => a.clone(),
                _ => unreachable!("chunks of two"),
            })
            .collect();
    }
    json!({
        "name": name,
        "variables": [{"name": "a", "kind": "se2"}],
        "parameters": [{"name": "m", "kind": "vector", "len": 256}],
        "residual": {"norm": [terms[0]]}
    })
}

fn heavies(prefix: &str, count: usize) -> Vec<Value> {
    (0..count)
        .map(|k| heavy(&format!("{prefix}{k}"), k))
        .collect()
}

/// Three poses and one factor of type `ty` on each.
fn batch_of(ty: &str, first: u64) -> Value {
    let variables: Vec<Value> = (first..first + 3)
        .map(|k| json!({"key": k, "kind": "se2", "value": [0.1 * k as f64, 0.2, 0.0]}))
        .collect();
    let factors: Vec<Value> = (first..first + 3)
        .map(|k| json!({"type": ty, "keys": [k], "measurement": vec![0.01; 256], "information": [1.0]}))
        .collect();
    json!({"variables": variables, "factors": factors})
}

async fn create_with(
    c: &reqwest::Client,
    s: &TestServer,
    name: &str,
    types: &[Value],
) -> (u16, Value) {
    post(
        c,
        &s.url("/v1/sessions"),
        &json!({"session": name, "kind": "pose_graph_2d", "factor_types": types,
                "auto_optimize": {"policy": "manual"}}),
    )
    .await
}

async fn memory_bytes(c: &reqwest::Client, s: &TestServer, name: &str) -> f64 {
    let (status, v) = get(c, &s.url(&format!("/v1/sessions/{name}"))).await;
    assert_eq!(status, 200, "{v}");
    v["memory_bytes"].as_f64().expect("memory_bytes")
}

async fn metric(c: &reqwest::Client, s: &TestServer, name: &str) -> Option<f64> {
    let text = c
        .get(s.url("/metrics"))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    text.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
}

fn rss(s: &TestServer) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{}/status", s.pid())).unwrap();
    let line = status.lines().find(|l| l.starts_with("VmRSS:")).unwrap();
    line.split_whitespace()
        .nth(1)
        .unwrap()
        .parse::<u64>()
        .unwrap()
        << 10
}

#[tokio::test(flavor = "multi_thread")]
async fn types_are_counted_in_memory_bytes_and_identical_ones_compiled_once() {
    let s = TestServer::start(&["--no-zenoh", "--no-journal"]);
    let c = client();
    let types = heavies("heavy_", 4);
    let (status, v) = create_with(&c, &s, "plain", &[]).await;
    assert_eq!(status, 201, "{v}");
    let plain = memory_bytes(&c, &s, "plain").await;
    let idle = rss(&s);
    let (status, v) = create_with(&c, &s, "first", &types).await;
    assert_eq!(status, 201, "{v}");
    let first_growth = rss(&s).saturating_sub(idle);
    let with_types = memory_bytes(&c, &s, "first").await;
    // Four types of ~98 000 slots: at least their tapes (16-byte operations and a flag).
    assert!(
        with_types - plain > 4.0 * 98_000.0 * 17.0,
        "memory_bytes {with_types} with the types, {plain} without"
    );
    let after_first = rss(&s);
    for k in 0..4 {
        let (status, v) = create_with(&c, &s, &format!("again{k}"), &types).await;
        assert_eq!(status, 201, "{v}");
    }
    let rest_growth = rss(&s).saturating_sub(after_first);
    // Each session is charged its types in full…
    for k in 0..4 {
        let charged = memory_bytes(&c, &s, &format!("again{k}")).await;
        assert!(
            (charged - with_types).abs() < 0.01 * with_types,
            "{charged} vs {with_types}"
        );
    }
    // …but the server compiled and holds them once.
    assert_eq!(
        metric(&c, &s, "factord_factor_type_compiles_total").await,
        Some(4.0)
    );
    assert_eq!(
        metric(&c, &s, "factord_factor_type_reuses_total").await,
        Some(16.0)
    );
    assert_eq!(metric(&c, &s, "factord_factor_types").await, Some(4.0));
    let type_bytes = metric(&c, &s, "factord_factor_type_bytes").await.unwrap();
    assert!(
        (type_bytes - (with_types - plain)).abs() < 0.05 * type_bytes,
        "{type_bytes}"
    );
    let all_sessions = metric(&c, &s, "factord_session_memory_bytes")
        .await
        .unwrap();
    assert!(
        all_sessions < 2.0 * with_types,
        "{all_sessions} counts the shared types once"
    );
    eprintln!(
        "RSS growth: first session {} MB, four more with the same types {} MB; memory_bytes {} MB",
        first_growth >> 20,
        rest_growth >> 20,
        (with_types as u64) >> 20
    );
    assert!(
        rest_growth < first_growth / 2,
        "four sessions sharing the types grew RSS by {rest_growth}, the first by {first_growth}"
    );
    // The shared types build factors in every session.
    for name in ["first", "again3"] {
        let (status, v) = post(
            &c,
            &s.url(&format!("/v1/sessions/{name}/batches")),
            &batch_of("heavy_1", 0),
        )
        .await;
        assert_eq!(status, 200, "{v}");
    }
    // Once no session holds them, they are freed.
    for name in ["first", "again0", "again1", "again2", "again3"] {
        let r = c
            .delete(s.url(&format!("/v1/sessions/{name}")))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200);
    }
    let deadline = Instant::now() + Duration::from_secs(10);
    while metric(&c, &s, "factord_factor_types").await != Some(0.0) {
        assert!(
            Instant::now() < deadline,
            "types still held after every session was deleted"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn type_memory_and_compile_time_are_bounded_with_413s_naming_factor_types() {
    // Four large types hold ~15.6 MB, three ~11.7: a session may hold 12 MiB, the server 20.
    let s = start_with_limits(&json!({
        "max_factor_type_bytes_per_session": 12 << 20,
        "max_factor_type_bytes": 20 << 20,
    }));
    let c = client();
    let (status, v) = create_with(&c, &s, "four", &heavies("big_", 4)).await;
    assert_eq!(status, 413, "{v}");
    assert_eq!(v["error"]["code"], "factor_types_too_large", "{v}");
    assert_eq!(v["error"]["field"], "factor_types", "{v}");
    let (status, v) = get(&c, &s.url("/v1/sessions/four")).await;
    assert_eq!(status, 404, "nothing created: {v}");

    let (status, v) = create_with(&c, &s, "three", &heavies("big_", 3)).await;
    assert_eq!(status, 201, "{v}");
    // A fourth declared later meets the same bound.
    let (status, v) = post(
        &c,
        &s.url("/v1/sessions/three/factor_types"),
        &json!({"factor_types": [heavy("big_3", 3)]}),
    )
    .await;
    assert_eq!(status, 413, "{v}");
    assert_eq!(v["error"]["code"], "factor_types_too_large", "{v}");
    assert_eq!(v["error"]["field"], "factor_types", "{v}");

    // Three other types would take the server past its 20 MiB…
    let (status, v) = create_with(&c, &s, "others", &heavies("other_", 3)).await;
    assert_eq!(status, 413, "{v}");
    assert_eq!(v["error"]["code"], "factor_types_server_full", "{v}");
    assert_eq!(v["error"]["field"], "factor_types", "{v}");
    // …the same three are shared at no cost.
    let (status, v) = create_with(&c, &s, "same", &heavies("big_", 3)).await;
    assert_eq!(status, 201, "{v}");
    let (status, v) = post(
        &c,
        &s.url("/v1/sessions/same/batches"),
        &batch_of("big_2", 0),
    )
    .await;
    assert_eq!(status, 200, "{v}");
    s.assert_no_panic();
    drop(s);

    // Compiling counts against the admission time: eight large types take most of a second.
    let s = start_with_limits(&json!({"max_admission_ms": 50}));
    let (status, v) = create_with(&c, &s, "slow", &heavies("slow_", 8)).await;
    assert_eq!(status, 413, "{v}");
    assert_eq!(v["error"]["code"], "factor_types_too_costly", "{v}");
    assert_eq!(v["error"]["field"], "factor_types", "{v}");
    let (status, v) = create_with(&c, &s, "small", &[common::user_between_se2()]).await;
    assert_eq!(status, 201, "{v}");
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn a_restart_with_large_types_answers_at_once_and_recovers_them_in_the_background() {
    // 10 sessions × 12 types of their own: 120 compiles, seconds of work the old start-up did
    // before opening HTTP.
    const SESSIONS: usize = 10;
    let s = TestServer::start(&[]);
    let c = client();
    let mut before = Vec::new();
    for k in 0..SESSIONS {
        let name = format!("r{k}");
        let (status, v) = create_with(&c, &s, &name, &heavies(&format!("s{k}_"), 12)).await;
        assert_eq!(status, 201, "{v}");
        let (status, v) = post(
            &c,
            &s.url(&format!("/v1/sessions/{name}/batches")),
            &batch_of(&format!("s{k}_5"), 0),
        )
        .await;
        assert_eq!(status, 200, "{v}");
        let (_, stats) = get(&c, &s.url(&format!("/v1/sessions/{name}"))).await;
        before.push(stats);
    }
    let state_dir = s.state_dir.clone();
    s.kill();

    let started = Instant::now();
    let s = TestServer::start_at(&state_dir, &[], &[]);
    let (status, v) = get(&c, &s.url("/v1/health")).await;
    let health = started.elapsed();
    assert_eq!(status, 200, "{v}");
    eprintln!(
        "restart: /health answered {:.2} s after the start",
        health.as_secs_f64()
    );
    assert!(
        health < Duration::from_secs(2),
        "HTTP down for {health:?} at start"
    );
    // Every session is listed at once; one still recovering refuses writes with 503.
    let (status, listed) = get(&c, &s.url("/v1/sessions")).await;
    assert_eq!(status, 200);
    assert_eq!(
        listed["sessions"].as_array().unwrap().len(),
        SESSIONS,
        "{listed}"
    );
    let last = format!("r{}", SESSIONS - 1);
    let (_, stats) = get(&c, &s.url(&format!("/v1/sessions/{last}"))).await;
    if stats["recovering"] == true {
        let (status, v) = post(
            &c,
            &s.url(&format!("/v1/sessions/{last}/batches")),
            &batch_of("s9_1", 10),
        )
        .await;
        assert_eq!(status, 503, "{v}");
    }
    for (k, before) in before.iter().enumerate() {
        let name = format!("r{k}");
        let (after, seconds) = common::server::recovered(&c, &s, &name, started).await;
        if k == SESSIONS - 1 {
            eprintln!("restart: {SESSIONS} sessions writable {seconds:.2} s after the start");
        }
        for field in ["sequence", "num_variables", "num_factors", "factor_types"] {
            assert_eq!(after[field], before[field], "{name}.{field}");
        }
        // The recompiled types are counted again (12 × ~4 MB).
        assert!(
            after["memory_bytes"].as_f64().unwrap() > 12.0 * 3e6,
            "{after}"
        );
        assert_eq!(after["corrupt"], false, "{after}");
        let (status, v) = post(
            &c,
            &s.url(&format!("/v1/sessions/{name}/batches")),
            &batch_of(&format!("s{k}_2"), 10),
        )
        .await;
        assert_eq!(status, 200, "{v}");
    }
    s.assert_no_panic();
}
