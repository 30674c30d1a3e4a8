//! The stream over HTTP: one `POST /v1/sessions/<s>/batches?wait=true` per pose, the next sent
//! once the previous answer says the estimate reflects it.

use std::time::{Duration, Instant};

use serde_json::Value;

use crate::common::server::TestServer;
use crate::{MemoryAt, Streamed};

/// Streams `bodies` (serialised batches, prepared before the clock starts) into `session`.
/// Latency of an update: from sending the request to having read and parsed the whole answer;
/// when the answer does not say `solved: true` (a wait that timed out), the time until the
/// session's `solved_sequence` reaches the batch is added (polled every millisecond, counted in
/// `fallbacks`). Every `memory_every` updates (outside the clock), the server's peak resident
/// memory so far and the session's own estimate are recorded in `Streamed::memory`.
pub async fn stream(
    s: &TestServer,
    session: &str,
    bodies: &[String],
    memory_every: Option<usize>,
) -> Streamed {
    let client = reqwest::Client::builder()
        .timeout(Duration::from_secs(300))
        .pool_max_idle_per_host(1)
        .build()
        .expect("http client");
    let url = s.url(&format!("/v1/sessions/{session}/batches?wait=true"));
    let stats_url = s.url(&format!("/v1/sessions/{session}"));
    let mut latencies_ms = Vec::with_capacity(bodies.len());
    let mut fallbacks = 0;
    let (mut slow_exact, mut slow_provisional) = (0usize, 0usize);
    let mut memory = Vec::new();
    let start = Instant::now();
    for (i, body) in bodies.iter().enumerate() {
        let t = Instant::now();
        let resp = client
            .post(&url)
            .header("content-type", "application/json")
            .body(body.clone())
            .send()
            .await
            .unwrap_or_else(|e| panic!("pose {i}: request failed: {e:?}"));
        let status = resp.status().as_u16();
        let bytes = resp.bytes().await.expect("answer body");
        let reply: Value = serde_json::from_slice(&bytes).expect("a JSON answer");
        assert_eq!(status, 200, "pose {i}: {reply}");
        if reply["solved"] != true {
            fallbacks += 1;
            let sequence = reply["sequence"].as_u64().expect("ack has a sequence");
            let deadline = Instant::now() + Duration::from_secs(300);
            loop {
                let stats = session_stats(&client, &stats_url).await;
                if stats["solved_sequence"].as_u64().unwrap_or(0) >= sequence {
                    break;
                }
                assert!(Instant::now() < deadline, "pose {i} never solved: {stats}");
                tokio::time::sleep(Duration::from_millis(1)).await;
            }
        }
        let ms = t.elapsed().as_secs_f64() * 1e3;
        // With a latency budget: which kind of answer the slow ones were.
        if ms > 5.0 {
            match reply["exact"].as_bool() {
                Some(true) => slow_exact += 1,
                Some(false) => slow_provisional += 1,
                None => {}
            }
        }
        latencies_ms.push(ms);
        if memory_every.is_some_and(|every| (i + 1) % every == 0) {
            let stats = session_stats(&client, &stats_url).await;
            memory.push(MemoryAt {
                updates: i + 1,
                peak_rss_kb: crate::proc_status_kb(s.pid(), "VmHWM"),
                session_memory_bytes: stats["memory_bytes"].as_u64(),
            });
        }
    }
    if slow_exact + slow_provisional > 0 {
        eprintln!(
            "answers over 5 ms: {slow_exact} exact, {slow_provisional} provisional (budget sessions)"
        );
    }
    Streamed {
        latencies_ms,
        wall_seconds: start.elapsed().as_secs_f64(),
        fallbacks,
        poses_received: None,
        memory,
    }
}

/// The session's statistics (`GET /v1/sessions/<s>`).
async fn session_stats(client: &reqwest::Client, url: &str) -> Value {
    client
        .get(url)
        .send()
        .await
        .expect("stats")
        .json()
        .await
        .expect("stats JSON")
}
