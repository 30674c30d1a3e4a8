//! Thousands of half-open connections (a partial request line, then nothing) against a real
//! server allowed only 4096 open files: health keeps answering in under a second, other routes
//! get 503 `too_many_connections`, memory stays bounded, and the held sockets are closed after
//! the header timeout (catalogue row T13).

use crate::common;

use std::time::{Duration, Instant};

use common::server::TestServer;
use serde_json::Value;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// The server's open-file limit: small enough that the attack below exceeds it.
const SERVER_FILES: u64 = 4096;
const ATTACK_CONNECTIONS: u64 = 5000;
/// `http.header_timeout_ms` here: longer than opening the connections takes on a busy machine,
/// so they are all still held while health is measured.
const HEADER_TIMEOUT: Duration = Duration::from_secs(20);

/// Raises this process's soft open-file limit to its hard limit; returns the soft limit.
fn raise_own_file_limit() -> u64 {
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit and setrlimit only read and write the struct passed in.
    unsafe {
        assert_eq!(libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit), 0);
        limit.rlim_cur = limit.rlim_max;
        if libc::setrlimit(libc::RLIMIT_NOFILE, &limit) != 0 {
            libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit);
        }
    }
    limit.rlim_cur as u64
}

/// A connection that sends the start of a request line and nothing more.
async fn half_open(address: &str) -> Option<TcpStream> {
    let open = async {
        let mut stream = TcpStream::connect(address).await.ok()?;
        stream.write_all(b"GET /v1/hea").await.ok()?;
        Some(stream)
    };
    tokio::time::timeout(Duration::from_secs(2), open)
        .await
        .ok()
        .flatten()
}

/// One health request on a fresh connection: its latency, or why it failed.
async fn health(url: &str) -> Result<Duration, String> {
    let client = reqwest::Client::builder()
        .timeout(Duration::from_secs(5))
        .build()
        .map_err(|e| e.to_string())?;
    let started = Instant::now();
    let resp = client.get(url).send().await.map_err(|e| format!("{e:?}"))?;
    let status = resp.status();
    let body: Value = resp.json().await.map_err(|e| format!("{e:?}"))?;
    if status != 200 || body["status"] != "ok" {
        return Err(format!("{status}: {body}"));
    }
    Ok(started.elapsed())
}

fn rss_kib(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap_or(0)
}

#[tokio::test(flavor = "multi_thread")]
async fn half_open_connections_leave_health_answering() {
    let own = raise_own_file_limit();
    let attack = ATTACK_CONNECTIONS.min(own.saturating_sub(512));
    if attack <= SERVER_FILES {
        assert!(
            std::env::var("CI").is_err(),
            "open-file limit {own} too small"
        );
        println!("skipping: this process may open only {own} files");
        return;
    }
    let config = common::temp_dir("connections").join("config.json");
    let timeout_ms = HEADER_TIMEOUT.as_millis();
    let http = format!(r#"{{"http": {{"header_timeout_ms": {timeout_ms}}}}}"#);
    std::fs::write(&config, http).unwrap();
    let config = config.display().to_string();
    let s = TestServer::start_with_file_limit(&["--no-zenoh", "--config", &config], SERVER_FILES);
    let address = s.http.trim_start_matches("http://").to_string();
    let rss_before = rss_kib(s.pid());

    // Open the connections 200 at a time, for at most 15 s (a server out of files stops
    // accepting and connects time out).
    let started = Instant::now();
    let mut held = Vec::new();
    while (held.len() as u64) < attack && started.elapsed() < Duration::from_secs(15) {
        let wave = (attack - held.len() as u64).min(200);
        let opened = futures_util::future::join_all((0..wave).map(|_| half_open(&address))).await;
        held.extend(opened.into_iter().flatten());
    }
    println!(
        "{} half-open connections held by the client ({:.1} s to open)",
        held.len(),
        started.elapsed().as_secs_f64()
    );

    // Health, several times while they are held: each on a fresh connection, under a second.
    let url = s.url("/v1/health");
    let mut latencies = Vec::new();
    for _ in 0..5 {
        let latency = health(&url).await;
        println!("health while held: {latency:?}");
        let latency = latency.unwrap_or_else(|e| panic!("health failed: {e}"));
        assert!(latency < Duration::from_secs(1), "health took {latency:?}");
        latencies.push(latency);
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    // Anything else beyond the cap is refused with the JSON error body, not left hanging.
    let resp = common::server::client()
        .get(s.url("/v1/sessions"))
        .send()
        .await
        .expect("an answer beyond the cap");
    let status = resp.status();
    let v: Value = resp.json().await.unwrap();
    assert_eq!(status, 503, "{v}");
    assert_eq!(v["error"]["code"], "too_many_connections", "{v}");

    let rss = rss_kib(s.pid());
    println!(
        "server RSS {} MiB while held (at start {} MiB); health max {:?}",
        rss / 1024,
        rss_before / 1024,
        latencies.iter().max()
    );
    assert!(rss < 256 * 1024, "server RSS {rss} KiB");

    // The server closes the held connections once the header timeout has passed.
    let mut first = held.swap_remove(0);
    let mut byte = [0u8; 1];
    let deadline = HEADER_TIMEOUT + Duration::from_secs(5);
    let left = deadline.saturating_sub(started.elapsed());
    let read = tokio::time::timeout(left, first.read(&mut byte)).await;
    assert!(
        matches!(read, Ok(Ok(0)) | Ok(Err(_))),
        "a half-open connection was still open after {deadline:?}: {read:?}"
    );
    drop(held);
    if let Err(e) = health(&url).await {
        panic!("health once the connections were dropped: {e}");
    }
    s.assert_no_panic();
}
