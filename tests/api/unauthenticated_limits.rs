//! What a client without a token can hold, against a real `factord serve` with tokens on, over
//! real sockets on 127.0.0.1 (issue 52, items 3 and 6; catalogue rows T19–T21):
//!
//! - `POST /v1/login` connections that announce a body and stall cannot keep authenticated
//!   clients out: a lone one is answered 408 `body_timeout` after the header timeout, and while
//!   more of them than the connection cap are held (and re-opened as they close), every
//!   authenticated request on a fresh connection is answered 200 within a deadline;
//! - an unauthenticated body is bounded before it is read: 8 × 200 MB logins are refused by
//!   their `Content-Length` (413, field `content-length`) without the server's peak memory
//!   growing, and a chunked one is cut off once past the bound (413, field `body`).

use crate::common;

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::server::TestServer;
use serde_json::Value;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

const ALICE: &str = "alice-0123456789abcdef";
/// `http.max_connections` here: small, so a few dozen sockets exceed it.
const CAP: usize = 32;
/// `http.header_timeout_ms` here, also the deadline of an unauthenticated body.
const HEADER_TIMEOUT: Duration = Duration::from_secs(2);

fn server() -> TestServer {
    let dir = common::temp_dir("unauthenticated");
    let tokens = dir.join("tokens");
    std::fs::write(&tokens, format!("alice {ALICE}\n")).unwrap();
    let config = dir.join("config.json");
    let http = format!(
        r#"{{"http": {{"max_connections": {CAP}, "header_timeout_ms": {}}}}}"#,
        HEADER_TIMEOUT.as_millis()
    );
    std::fs::write(&config, http).unwrap();
    TestServer::start(&[
        "--no-zenoh",
        "--tokens-file",
        &tokens.display().to_string(),
        "--config",
        &config.display().to_string(),
    ])
}

/// A login head announcing `length` bytes of body, and the first few of them.
fn stalled_login(length: u64) -> Vec<u8> {
    format!(
        "POST /v1/login HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n\
         Content-Length: {length}\r\n\r\n{{\"token\": \""
    )
    .into_bytes()
}

/// Everything the server sends until it closes (or `limit` passes): status and JSON body.
async fn answer(stream: &mut TcpStream, limit: Duration) -> Option<(u16, Value)> {
    let mut bytes = Vec::new();
    let _ = tokio::time::timeout(limit, stream.read_to_end(&mut bytes)).await;
    let text = String::from_utf8_lossy(&bytes);
    let status = text.get(9..12)?.parse().ok()?;
    let body = text.split_once("\r\n\r\n").map_or("", |(_, b)| b);
    Some((status, serde_json::from_str(body).unwrap_or(Value::Null)))
}

fn field_of(v: &Value) -> (&str, &str) {
    let e = &v["error"];
    (
        e["code"].as_str().unwrap_or("?"),
        e["field"].as_str().unwrap_or("?"),
    )
}

/// One stalled login, re-opened whenever the server closes it, until `stop`.
async fn keep_stalling(
    address: String,
    length: u64,
    stop: Arc<AtomicBool>,
    opened: Arc<AtomicUsize>,
) {
    while !stop.load(Ordering::Relaxed) {
        if let Ok(mut stream) = TcpStream::connect(&address).await {
            opened.fetch_add(1, Ordering::Relaxed);
            if stream.write_all(&stalled_login(length)).await.is_ok() {
                let mut sink = [0u8; 1024];
                let held =
                    async { while matches!(stream.read(&mut sink).await, Ok(n) if n > 0) {} };
                let _ = tokio::time::timeout(Duration::from_secs(30), held).await;
            }
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// `GET /v1/sessions` with the token on a fresh connection: its status and latency.
async fn authenticated_read(url: &str) -> (Result<u16, String>, Duration) {
    let client = reqwest::Client::builder()
        .pool_max_idle_per_host(0)
        .timeout(Duration::from_secs(5))
        .build()
        .unwrap();
    let started = Instant::now();
    let status = client
        .get(url)
        .bearer_auth(ALICE)
        .send()
        .await
        .map(|r| r.status().as_u16())
        .map_err(|e| format!("{e:?}"));
    (status, started.elapsed())
}

#[tokio::test(flavor = "multi_thread")]
async fn stalled_logins_leave_authenticated_clients_served() {
    let s = server();
    let address = s.http.trim_start_matches("http://").to_string();

    // A lone stalled login is answered 408 once the header timeout has passed, and closed.
    let mut lone = TcpStream::connect(&address).await.unwrap();
    lone.write_all(&stalled_login(1000)).await.unwrap();
    let started = Instant::now();
    let lone = answer(&mut lone, HEADER_TIMEOUT + Duration::from_secs(3)).await;
    let took = started.elapsed();
    let (status, v) = lone.unwrap_or_else(|| panic!("no answer to a stalled login in {took:?}"));
    assert_eq!(
        (status, field_of(&v)),
        (408, ("body_timeout", "body")),
        "{v}"
    );
    assert!(took < HEADER_TIMEOUT + Duration::from_secs(2), "{took:?}");

    // Half again as many stalled logins as the cap, re-opened as they close; half announce a
    // body under the unauthenticated bound, half 100 MB.
    let stop = Arc::new(AtomicBool::new(false));
    let opened = Arc::new(AtomicUsize::new(0));
    let attackers: Vec<_> = (0..CAP + CAP / 2)
        .map(|i| {
            let length = if i % 2 == 0 { 1000 } else { 100_000_000 };
            let (stop, opened) = (Arc::clone(&stop), Arc::clone(&opened));
            tokio::spawn(keep_stalling(address.clone(), length, stop, opened))
        })
        .collect();
    tokio::time::sleep(Duration::from_millis(500)).await;

    // Authenticated reads on fresh connections, for three header timeouts: all answered.
    let url = s.url("/v1/sessions");
    let mut answers = Vec::new();
    let started = Instant::now();
    while started.elapsed() < 3 * HEADER_TIMEOUT {
        answers.push(authenticated_read(&url).await);
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    stop.store(true, Ordering::Relaxed);
    let mut latencies: Vec<Duration> = answers.iter().map(|(_, d)| *d).collect();
    latencies.sort();
    println!(
        "{} authenticated reads during the attack ({} attacking connections opened): \
         median {:?}, max {:?}; answers {:?}",
        answers.len(),
        opened.load(Ordering::Relaxed),
        latencies[latencies.len() / 2],
        latencies.last().unwrap(),
        answers.iter().map(|(s, _)| s.clone()).collect::<Vec<_>>()
    );
    for (status, latency) in &answers {
        assert_eq!(status, &Ok(200), "an authenticated read during the attack");
        assert!(*latency < Duration::from_secs(2), "took {latency:?}");
    }
    for attacker in attackers {
        attacker.abort();
    }
    s.assert_no_panic();
}

/// The server's peak resident memory so far, KiB.
fn peak_rss_kib(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap_or(0)
}

/// Sends a login announcing `total` bytes and then as much of them as the server takes.
async fn flood_login(address: String, total: u64) {
    let Ok(mut stream) = TcpStream::connect(&address).await else {
        return;
    };
    let mut head = stalled_login(total);
    head.truncate(head.len() - b"{\"token\": \"".len());
    let chunk = vec![b' '; 1 << 20];
    let send = async {
        stream.write_all(&head).await?;
        let mut sent = 0;
        while sent < total {
            let n = chunk.len().min((total - sent) as usize);
            stream.write_all(&chunk[..n]).await?;
            sent += n as u64;
        }
        Ok::<_, std::io::Error>(())
    };
    let _ = tokio::time::timeout(Duration::from_secs(30), send).await;
}

#[tokio::test(flavor = "multi_thread")]
async fn unauthenticated_bodies_are_bounded_before_they_are_read() {
    let s = server();
    let address = s.http.trim_start_matches("http://").to_string();

    // Refused by its Content-Length alone, before a byte of the body is read.
    let mut head_only = TcpStream::connect(&address).await.unwrap();
    let mut head = stalled_login(200_000_000);
    head.truncate(head.len() - b"{\"token\": \"".len());
    head_only.write_all(&head).await.unwrap();
    let refused = answer(&mut head_only, Duration::from_secs(3)).await;
    let (status, v) = refused.expect("an answer to the head alone");
    assert_eq!(
        (status, field_of(&v)),
        (413, ("body_too_large", "content-length")),
        "{v}"
    );

    // A chunked body is cut off once past the bound.
    let mut chunked = TcpStream::connect(&address).await.unwrap();
    let request = format!(
        "POST /v1/login HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n\
         Transfer-Encoding: chunked\r\n\r\n1388\r\n{}",
        " ".repeat(5000)
    );
    chunked.write_all(request.as_bytes()).await.unwrap();
    let refused = answer(&mut chunked, Duration::from_secs(3)).await;
    let (status, v) = refused.expect("an answer to a chunked body past the bound");
    assert_eq!(
        (status, field_of(&v)),
        (413, ("body_too_large", "body")),
        "{v}"
    );

    // 8 × 200 MB at once: the server's peak memory does not grow with them.
    let before = peak_rss_kib(s.pid());
    let started = Instant::now();
    let floods = (0..8).map(|_| tokio::spawn(flood_login(address.clone(), 200_000_000)));
    futures_util::future::join_all(floods).await;
    let after = peak_rss_kib(s.pid());
    println!(
        "8 x 200 MB unauthenticated logins: {:.1} s; server peak RSS {} MiB before, {} MiB after",
        started.elapsed().as_secs_f64(),
        before / 1024,
        after / 1024
    );
    assert!(
        after < before + 64 * 1024,
        "peak RSS grew from {before} KiB to {after} KiB"
    );

    // And the server still answers a valid login.
    let c = common::server::client();
    let login = serde_json::json!({ "token": ALICE });
    let (status, v) = common::server::post(&c, &s.url("/v1/login"), &login).await;
    assert_eq!(status, 200, "{v}");
    s.assert_no_panic();
}
