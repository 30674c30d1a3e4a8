//! Streams that cannot lose silently: a full-rate zenoh stream gets an acknowledgement (or a
//! cumulative one covering it) for every batch, and a subscriber that falls behind gets a
//! `lagged` marker with every producer's progress and then the latest value of every variable
//! changed meanwhile, so what it holds ends equal to the estimate. Nor do they run ahead of the
//! journal: nothing reflecting a batch is published before its acknowledgement. And what a
//! client waits on is sent at once (zenoh's express), never dropped.

use crate::common;

use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::server::{client, create, g2o_batches, get, post, zenoh_get, zenoh_peer, TestServer};
use factord::api::poses_binary;
use serde_json::{json, Value};
use zenoh::qos::CongestionControl;

/// `input_M3500_g2o` as streaming batches (a generated Manhattan graph of 3500 poses when the
/// data is missing), numbered by producer `robot`.
fn m3500_batches() -> Vec<Value> {
    let text = common::data_file("2d/carlone/input_M3500_g2o.g2o")
        .map(|p| std::fs::read_to_string(p).unwrap())
        .unwrap_or_else(|| common::synthetic_manhattan(3500, 17));
    with_producer(g2o_batches(&text))
}

/// `batches` numbered 1, 2, 3, … by producer `robot`.
fn with_producer(mut batches: Vec<Value>) -> Vec<Value> {
    for (i, b) in batches.iter_mut().enumerate() {
        b["producer"] = json!("robot");
        b["producer_seq"] = json!(i + 1);
    }
    batches
}

/// An odometry chain of `poses` poses as streaming batches (cheap to apply: many events per
/// second), numbered by producer `robot`.
fn odometry_batches(poses: usize) -> Vec<Value> {
    let mut text = String::from("VERTEX_SE2 0 0 0 0\n");
    for k in 1..poses {
        text += &format!(
            "VERTEX_SE2 {k} {k} 0 0\nEDGE_SE2 {} {k} 1 0 0.001 400 0 0 400 0 2500\n",
            k - 1
        );
    }
    with_producer(g2o_batches(&text))
}

/// What a subscriber of `<p>/<session>/out/**` saw: acknowledged producer numbers, lagged
/// markers (by key) and the highest cumulative `accepted_through`.
#[derive(Default, Debug)]
struct Seen {
    acked: BTreeSet<u64>,
    markers: Vec<(String, Value)>,
    accepted_through: u64,
    events: usize,
}

impl Seen {
    fn take(&mut self, key: &str, event: Value) {
        self.events += 1;
        match event["type"].as_str() {
            Some("ack") => {
                let number = event["producer_seq"]
                    .as_u64()
                    .or(event["sequence"].as_u64());
                self.acked.insert(number.unwrap());
                let through = event["accepted_through"].as_u64().unwrap_or(0);
                self.accepted_through = self.accepted_through.max(through);
            }
            Some("lagged") => {
                let through = event["producers"]["robot"].as_u64().unwrap_or(0);
                self.accepted_through = self.accepted_through.max(through);
                self.markers.push((key.to_string(), event));
            }
            _ => {}
        }
    }

    /// Batches acknowledged one by one or covered by a cumulative acknowledgement.
    fn covered(&self) -> usize {
        let through = self.accepted_through;
        through as usize + self.acked.iter().filter(|&&s| s > through).count()
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn full_rate_zenoh_stream_acknowledges_every_batch() {
    // FACTORD_STREAM_POSES=n: a generated Manhattan graph of n poses instead (measurements).
    let batches = match std::env::var("FACTORD_STREAM_POSES") {
        Ok(n) => with_producer(g2o_batches(&common::synthetic_manhattan(
            n.parse().unwrap(),
            17,
        ))),
        Err(_) => m3500_batches(),
    };
    let n = batches.len();
    let s = TestServer::start(&[]);
    let c = client();
    create(&c, &s, &json!({"session": "t7", "kind": "pose_graph_2d"})).await;
    let z = zenoh_peer(&s.zenoh).await;
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
    let _out = z
        .declare_subscriber("factord/t7/out/**")
        .callback(move |sample| {
            let event: Value = serde_json::from_slice(&sample.payload().to_bytes()).unwrap();
            let _ = tx.send((sample.key_expr().to_string(), event));
        })
        .await
        .unwrap();
    let publisher = z
        .declare_publisher("factord/t7/in/batch")
        .congestion_control(CongestionControl::Block)
        .await
        .unwrap();
    // The server's peer answers queries once it knows this peer; give the subscription time.
    zenoh_get(&z, "factord/t7/estimate", None).await.unwrap();
    tokio::time::sleep(Duration::from_millis(500)).await;

    let start = Instant::now();
    for b in &batches {
        publisher.put(b.to_string()).await.unwrap();
    }
    let sent = start.elapsed();
    let mut seen = Seen::default();
    let mut last = Instant::now();
    while seen.covered() < n && last.elapsed() < Duration::from_secs(15) {
        match tokio::time::timeout(Duration::from_millis(200), rx.recv()).await {
            Ok(Some((key, event))) => {
                seen.take(&key, event);
                last = Instant::now();
            }
            Ok(None) => break,
            Err(_) => {}
        }
    }
    let covered_after = start.elapsed();
    let (_, info) = get(&c, &s.url("/v1/sessions/t7")).await;
    eprintln!(
        "full rate: {n} batches sent in {:.2} s; {} acks seen, {} covered (accepted_through {}), \
         {} lagged markers, all covered after {:.2} s; {} events; session sequence {}",
        sent.as_secs_f64(),
        seen.acked.len(),
        seen.covered(),
        seen.accepted_through,
        seen.markers.len(),
        covered_after.as_secs_f64(),
        seen.events,
        info["sequence"]
    );
    let log = s.stderr();
    eprintln!(
        "server warnings: {}",
        log.lines().filter(|l| l.contains("WARN")).count()
    );
    assert_eq!(info["sequence"], n, "every batch applied");
    assert_eq!(seen.covered(), n, "every batch acknowledged or covered");
    for (key, marker) in &seen.markers {
        assert_eq!(marker["session"], "t7", "{key}");
    }
    z.close().await.unwrap();
    s.assert_no_panic();
}

/// A batch is acknowledged once it is durable (`fsync always`, the default), and nothing that
/// reflects it is published before that: its solve runs while the fsync does, but the solve's
/// iterations, estimate and summary wait for it. Solving a short chain takes far less than an
/// fsync, so a solve publishing ahead of the journal would show within a few batches.
#[tokio::test(flavor = "multi_thread")]
async fn nothing_of_a_batch_is_published_before_its_acknowledgement() {
    let s = TestServer::start(&[]);
    let c = client();
    create(
        &c,
        &s,
        &json!({"session": "order", "kind": "pose_graph_2d"}),
    )
    .await;
    let mut sse = c
        .get(s.url("/v1/sessions/order/events"))
        .send()
        .await
        .unwrap();
    assert_eq!(sse.status(), 200);
    let batches = odometry_batches(300);
    let url = s.url("/v1/sessions/order/batches");
    for (i, b) in batches.iter().enumerate() {
        // Every third waits for its solve, so solves start both with and without a batch behind.
        let url = if i % 3 == 0 {
            format!("{url}?wait=true")
        } else {
            url.clone()
        };
        assert_eq!(post(&c, &url, b).await.0, 200);
    }
    let mut buffer = String::new();
    let events = read_sse_until_quiet(&mut sse, &mut buffer, Duration::from_secs(2)).await;
    let (mut acked, mut solved) = (0, 0);
    for (i, (name, data)) in events.iter().enumerate() {
        let Some(sequence) = data["sequence"].as_u64() else {
            continue;
        };
        if data["type"] == "ack" {
            acked = acked.max(sequence);
            continue;
        }
        assert!(
            sequence <= acked,
            "event {i} ({name}) reflects batch {sequence}, acknowledged only through {acked}: {data}"
        );
        if data["type"] == "summary" {
            solved = solved.max(sequence);
        }
    }
    assert_eq!(acked, batches.len() as u64, "every batch acknowledged");
    assert_eq!(solved, acked, "the last solve reflects every batch");
    s.assert_no_panic();
}

/// Where an SSE stream's bytes come from.
trait SseBytes {
    /// The next bytes, or `None` at the end of the stream.
    async fn next_bytes(&mut self) -> Option<Vec<u8>>;
}

impl SseBytes for reqwest::Response {
    async fn next_bytes(&mut self) -> Option<Vec<u8>> {
        self.chunk().await.ok().flatten().map(|b| b.to_vec())
    }
}

/// An SSE stream read straight off a socket whose receive buffer is fixed at [`RECEIVE_BUFFER`].
/// Through reqwest the kernel may grow an unread connection's buffer to megabytes (autotuning),
/// which then held the whole stream (about 7 700 events) and the server's never fell behind.
struct SmallBufferSse(tokio::net::TcpStream);

/// Above loopback's 64 KiB segment size. With 4 KB the window the reader opened by reading
/// was never worth announcing (less than a segment), so the server waited for its window
/// probes, backing off: under the full suite's load the stream stalled until the server's idle
/// timeout closed it (twice this stop, 75 KB unsent).
const RECEIVE_BUFFER: u32 = 128 << 10;

impl SmallBufferSse {
    /// `GET path` on the server as HTTP/1.0 (a body that ends with the connection, not
    /// chunked, so the bytes are the stream's own); returns the reader and the bytes of the
    /// stream read with the head.
    async fn open(s: &TestServer, path: &str) -> (Self, String) {
        use tokio::io::AsyncWriteExt;
        let addr: std::net::SocketAddr = s.http.trim_start_matches("http://").parse().unwrap();
        let socket = tokio::net::TcpSocket::new_v4().unwrap();
        socket.set_recv_buffer_size(RECEIVE_BUFFER).unwrap();
        let mut stream = socket.connect(addr).await.unwrap();
        let request = format!("GET {path} HTTP/1.0\r\nAccept: text/event-stream\r\n\r\n");
        stream.write_all(request.as_bytes()).await.unwrap();
        let mut reader = Self(stream);
        let mut head = String::new();
        while !head.contains("\r\n\r\n") {
            let bytes = reader.next_bytes().await.expect("the answer's head");
            head.push_str(&String::from_utf8_lossy(&bytes));
        }
        let (status_and_headers, rest) = head.split_once("\r\n\r\n").unwrap();
        assert!(
            status_and_headers.starts_with("HTTP/1.0 200")
                || status_and_headers.starts_with("HTTP/1.1 200"),
            "{status_and_headers}"
        );
        (reader, rest.to_string())
    }
}

impl SseBytes for SmallBufferSse {
    async fn next_bytes(&mut self) -> Option<Vec<u8>> {
        use tokio::io::AsyncReadExt;
        let mut bytes = vec![0; 16 * 1024];
        match self.0.read(&mut bytes).await {
            Ok(0) | Err(_) => None,
            Ok(n) => {
                bytes.truncate(n);
                Some(bytes)
            }
        }
    }
}

/// Reads SSE events (name, data) from `resp` until none came for `quiet`.
async fn read_sse_until_quiet(
    resp: &mut impl SseBytes,
    buffer: &mut String,
    quiet: Duration,
) -> Vec<(String, Value)> {
    let mut events = Vec::new();
    while let Ok(Some(bytes)) = tokio::time::timeout(quiet, resp.next_bytes()).await {
        buffer.push_str(&String::from_utf8_lossy(&bytes));
        while let Some(pos) = buffer.find("\n\n") {
            let block: String = buffer.drain(..pos + 2).collect();
            let (mut name, mut data) = (String::new(), String::new());
            for line in block.lines() {
                if let Some(v) = line.strip_prefix("event:") {
                    name = v.trim().into();
                } else if let Some(v) = line.strip_prefix("data:") {
                    data.push_str(v.trim());
                }
            }
            if !data.is_empty() {
                events.push((name, serde_json::from_str(&data).unwrap()));
            }
        }
    }
    events
}

/// The value of every variable of an estimate (GET estimate, or `poses` events in order).
fn apply_poses(values: &mut BTreeMap<u64, Value>, estimate: &Value) {
    for v in estimate["variables"].as_array().unwrap() {
        values.insert(v["key"].as_u64().unwrap(), v["value"].clone());
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_subscriber_that_falls_behind_gets_the_lagged_marker_and_the_latest_values() {
    // The reader's socket and the server's send buffer hold about 3 500 of the stream's ~8 000
    // events (with a 4 KB receive buffer); with the default 4 096 events of slack the reader
    // fell behind in some runs only (it read all 7 442 and 7 602 events without a marker in two
    // of six runs), so the test allows it less.
    falls_behind_and_resynchronises(json!({"max_subscriber_lag": 512})).await;
}

/// The same by bytes: the session keeps the default count of events, but only 256 KiB of them
/// (the stream's poses events hold far more): the reader finds the events it had not taken gone
/// and re-synchronises the same way.
#[tokio::test(flavor = "multi_thread")]
async fn a_subscriber_behind_by_more_than_the_retained_bytes_resynchronises() {
    falls_behind_and_resynchronises(json!({"max_subscriber_lag_bytes": 256 << 10})).await;
}

async fn falls_behind_and_resynchronises(limits: Value) {
    // Two producers, interleaved, over zenoh at full rate; the SSE reader reads nothing until
    // every batch is applied, so its stream overflows.
    let mut batches = m3500_batches();
    let (mut counts, n) = ([0u64; 2], batches.len());
    for (i, b) in batches.iter_mut().enumerate() {
        counts[i % 2] += 1;
        b["producer"] = json!(["a", "b"][i % 2]);
        b["producer_seq"] = json!(counts[i % 2]);
    }
    let config = common::temp_dir("lag").join("config.json");
    std::fs::write(&config, json!({ "limits": limits }).to_string()).unwrap();
    let s = TestServer::start(&["--config", config.to_str().unwrap()]);
    let c = client();
    create(&c, &s, &json!({"session": "lag", "kind": "pose_graph_2d"})).await;
    let (mut sse, mut buffer) = SmallBufferSse::open(&s, "/v1/sessions/lag/events").await;
    let z = zenoh_peer(&s.zenoh).await;
    let publisher = z
        .declare_publisher("factord/lag/in/batch")
        .congestion_control(CongestionControl::Block)
        .await
        .unwrap();
    zenoh_get(&z, "factord/lag/estimate", None).await.unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    for b in &batches {
        publisher.put(b.to_string()).await.unwrap();
    }
    let deadline = Instant::now() + Duration::from_secs(120);
    while get(&c, &s.url("/v1/sessions/lag")).await.1["sequence"] != n {
        assert!(
            Instant::now() < deadline,
            "the batches were not all applied"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let url = s.url("/v1/sessions/lag/optimize?wait=true");
    assert_eq!(post(&c, &url, &json!({})).await.0, 200);
    // Idle (past the polish that may follow): the estimate the re-synchronisation must give.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let mut before = BTreeMap::new();
    apply_poses(
        &mut before,
        &get(&c, &s.url("/v1/sessions/lag/estimate")).await.1,
    );

    // Now read: what the connection buffered, the marker, the re-synchronisation, the rest.
    let mut events = Vec::new();
    let mut held = BTreeMap::new();
    let mut estimate = BTreeMap::new();
    for _ in 0..5 {
        events.extend(read_sse_until_quiet(&mut sse, &mut buffer, Duration::from_secs(2)).await);
        held.clear();
        for (name, data) in &events {
            if name == "poses" {
                apply_poses(&mut held, data);
            }
        }
        let (status, body) = get(&c, &s.url("/v1/sessions/lag/estimate")).await;
        assert_eq!(status, 200);
        estimate.clear();
        apply_poses(&mut estimate, &body);
        if held == estimate {
            break;
        }
    }
    let markers: Vec<usize> = (0..events.len())
        .filter(|&i| events[i].0 == "lagged")
        .collect();
    eprintln!(
        "SSE reader: {} events read, {} lagged markers ({}), {} variables held",
        events.len(),
        markers.len(),
        markers
            .iter()
            .map(|&i| events[i].1["skipped"].to_string())
            .collect::<Vec<_>>()
            .join(", "),
        held.len()
    );
    assert!(!markers.is_empty(), "the reader never fell behind");
    // Under load the server's sender can fall behind the channel while the socket still has
    // room, and report that earlier lag first: every marker counts what was applied when it
    // was written, and the last one, written once the stalled reader reads again, everything.
    for &i in &markers {
        let m = &events[i].1;
        let (a, b) = (m["producers"]["a"].as_u64(), m["producers"]["b"].as_u64());
        assert_eq!(m["sequence"].as_u64(), a.zip(b).map(|(a, b)| a + b), "{m}");
    }
    let last = *markers.last().expect("a marker");
    let (at_marker, marker) = (last, &events[last].1);
    assert_eq!(marker["session"], "lag");
    assert_eq!(marker["sequence"], n, "{marker}");
    assert_eq!(marker["producers"], json!({"a": counts[0], "b": counts[1]}));
    assert!(marker["reflected_sequence"].as_u64().unwrap() <= n as u64);
    assert!(marker["skipped"].as_u64().unwrap() > 0);
    assert_eq!(
        events[at_marker + 1].0,
        "poses",
        "the re-synchronisation follows"
    );
    assert_eq!(
        held, estimate,
        "the stream's latest values are the estimate"
    );
    // Right after the re-synchronisation the reader holds the latest value of every variable
    // (the session was idle: what it holds is the estimate read before reading); before it,
    // what the connection had buffered is far from that.
    let mut at = BTreeMap::new();
    for (name, data) in &events[..at_marker] {
        if name == "poses" {
            apply_poses(&mut at, data);
        }
    }
    assert_ne!(at, before, "the reader had everything before the marker");
    apply_poses(&mut at, &events[at_marker + 1].1);
    assert_eq!(
        at, before,
        "the re-synchronisation holds every changed variable's latest value"
    );
    z.close().await.unwrap();
    s.assert_no_panic();
}

/// The socket buffers (bytes) of the stalled subscriber's link, each way. Loopback's defaults
/// grow to megabytes, which hold tens of thousands of small events: a stall would then fill
/// the kernel's buffers before the server's event channel.
const SOCKET_BUFFER: usize = 16 * 1024;

/// The longest the slow subscriber stalls (the server's zenoh waits longer: see
/// [`stall_tolerant_zenoh_config`]).
const MAX_STALL: Duration = Duration::from_secs(40);

/// A zenoh configuration file for the server whose subscriber stalls: small socket buffers,
/// and a blocked put or a silent peer tolerated for a minute (zenoh's defaults close the link
/// after 5 s of a blocked put, and the peer closes it after the server's 10 s lease without a
/// word, which a stalled reception cannot hear).
fn stall_tolerant_zenoh_config() -> String {
    let path = common::temp_dir("slow-zenoh").join("zenoh.json5");
    let config = json!({"transport": {"link": {
        "tcp": {"so_sndbuf": SOCKET_BUFFER, "so_rcvbuf": SOCKET_BUFFER},
        "tx": {
            "lease": 60_000,
            "queue": {"congestion_control": {"block": {"wait_before_close": 60_000_000}}},
        },
    }}});
    std::fs::write(&path, config.to_string()).unwrap();
    path.to_str().unwrap().to_string()
}

#[tokio::test(flavor = "multi_thread")]
async fn a_slow_zenoh_subscriber_gets_the_lagged_marker_on_every_topic() {
    let batches = odometry_batches(8000);
    let n = batches.len();
    let s = TestServer::start(&["--zenoh-config", &stall_tolerant_zenoh_config()]);
    let c = client();
    create(&c, &s, &json!({"session": "slow", "kind": "pose_graph_2d"})).await;
    let z = zenoh_peer(&format!("{}#so_rcvbuf={SOCKET_BUFFER}", s.zenoh)).await;
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
    let stalled = Arc::new(AtomicBool::new(false));
    let release = Arc::new(AtomicBool::new(false));
    // Both subscribers' callbacks run on this peer's one reception thread, in arrival order.
    let mut subscribers = Vec::new();
    for key in ["factord/slow/out/**", "factord/slow/bin/poses"] {
        let (tx, stalled, released) = (tx.clone(), Arc::clone(&stalled), Arc::clone(&release));
        let subscriber = z
            .declare_subscriber(key)
            .callback(move |sample| {
                // The first event stalls this peer's reception until the server has applied
                // and solved every batch, so the publisher falls behind by (nearly) the whole
                // stream, however fast or slow the machine.
                if !stalled.swap(true, Ordering::SeqCst) {
                    let deadline = Instant::now() + MAX_STALL;
                    while !released.load(Ordering::SeqCst) && Instant::now() < deadline {
                        std::thread::sleep(Duration::from_millis(10));
                    }
                }
                let _ = tx.send((sample.key_expr().to_string(), event_of(&sample)));
            })
            .await
            .unwrap();
        subscribers.push(subscriber);
    }
    let publisher = z
        .declare_publisher("factord/slow/in/batch")
        .congestion_control(CongestionControl::Block)
        .await
        .unwrap();
    zenoh_get(&z, "factord/slow/estimate", None).await.unwrap();
    tokio::time::sleep(Duration::from_millis(500)).await;
    for b in &batches {
        publisher.put(b.to_string()).await.unwrap();
    }
    let deadline = Instant::now() + MAX_STALL;
    while Instant::now() < deadline {
        let stats = get(&c, &s.url("/v1/sessions/slow")).await.1;
        if stats["solved_sequence"].as_u64().unwrap_or(0) >= n as u64 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    release.store(true, Ordering::SeqCst);
    let (mut seen, mut estimate) = (Seen::default(), BTreeMap::new());
    // The latest values the JSON and the binary estimates carried.
    let (mut held, mut held_binary) = (BTreeMap::new(), BTreeMap::new());
    let mut received = Vec::new();
    for _ in 0..10 {
        while let Ok(Some((key, event))) =
            tokio::time::timeout(Duration::from_secs(2), rx.recv()).await
        {
            if event["type"] == "estimate" {
                match key.contains("/bin/") {
                    true => apply_poses(&mut held_binary, &event),
                    false => apply_poses(&mut held, &event),
                }
            }
            if key.ends_with("/poses") {
                received.push(event["type"].as_str().unwrap().to_string());
            }
            seen.take(&key, event);
        }
        estimate.clear();
        apply_poses(
            &mut estimate,
            &get(&c, &s.url("/v1/sessions/slow/estimate")).await.1,
        );
        if seen.covered() == n && held == estimate && same_values(&held_binary, &estimate) {
            break;
        }
    }
    eprintln!(
        "slow zenoh subscriber: {} events, {} acks seen, {} covered, {} lagged markers \
         (the first after {} skipped events)",
        seen.events,
        seen.acked.len(),
        seen.covered(),
        seen.markers.len(),
        seen.markers
            .first()
            .map_or(Value::Null, |(_, m)| m["skipped"].clone())
    );
    assert!(!seen.markers.is_empty(), "the publisher never fell behind");
    // One marker per lag, on each of the session's topics (the binary poses too), identical.
    let topics = [
        "acks", "poses", "poses", "stats", "summary", "errors", "outliers",
    ];
    assert_eq!(seen.markers.len() % topics.len(), 0);
    for lag in seen.markers.chunks(topics.len()) {
        let keys: Vec<&str> = lag
            .iter()
            .map(|(k, _)| k.rsplit('/').next().unwrap())
            .collect();
        assert_eq!(keys, topics);
        assert!(lag[2].0.ends_with("/bin/poses"), "{:?}", lag[2].0);
        assert!(lag.iter().all(|(_, m)| m == &lag[0].1));
        let through = lag[0].1["producers"]["robot"].as_u64().unwrap();
        assert!(through > 0 && through <= n as u64);
    }
    // On `poses`, the first marker is followed by the re-synchronisation.
    let marker = received.iter().position(|t| t == "lagged").unwrap();
    let next = received[marker..].iter().find(|t| *t != "lagged");
    assert_eq!(
        next.map(String::as_str),
        Some("estimate"),
        "{:?}",
        &received[marker..]
    );
    assert_eq!(seen.covered(), n, "every batch acknowledged or covered");
    assert_eq!(
        held, estimate,
        "the published latest values are the estimate"
    );
    assert_same_values(&held_binary, &estimate);
    drop(subscribers);
    z.close().await.unwrap();
    s.assert_no_panic();
}

/// Whether the binary estimates' latest values are the estimate's, bit for bit.
fn same_values(binary: &BTreeMap<u64, Value>, estimate: &BTreeMap<u64, Value>) -> bool {
    first_difference(binary, estimate).is_none()
}

/// The first variable whose values differ, named (the maps are too long to print whole).
fn first_difference(
    binary: &BTreeMap<u64, Value>,
    estimate: &BTreeMap<u64, Value>,
) -> Option<String> {
    if binary.len() != estimate.len() {
        return Some(format!(
            "{} values against {}",
            binary.len(),
            estimate.len()
        ));
    }
    binary
        .iter()
        .zip(estimate)
        .find(|(a, b)| a != b)
        .map(|((ka, a), (kb, b))| format!("{ka}: {a} against {kb}: {b}"))
}

fn assert_same_values(binary: &BTreeMap<u64, Value>, estimate: &BTreeMap<u64, Value>) {
    if let Some(difference) = first_difference(binary, estimate) {
        panic!("the latest values published in binary are not the estimate: {difference}");
    }
}

/// A sample as a JSON event: JSON as it is, a binary estimate decoded into the JSON form.
fn event_of(sample: &zenoh::sample::Sample) -> Value {
    let bytes = sample.payload().to_bytes();
    if bytes.starts_with(poses_binary::MAGIC) {
        let session = sample.key_expr().as_str().split('/').nth(1).unwrap();
        let estimate = poses_binary::decode(&bytes, session).unwrap();
        let mut event = serde_json::to_value(estimate).unwrap();
        event["type"] = json!("estimate");
        return event;
    }
    serde_json::from_slice(&bytes).unwrap()
}

#[tokio::test(flavor = "multi_thread")]
async fn what_a_robot_waits_on_is_sent_at_once_and_never_dropped() {
    // Batched behind a large estimate, the summary that completes an update waited for zenoh's
    // batch to stop growing; iteration statistics may still be batched and dropped.
    let batches: Vec<Value> = m3500_batches().into_iter().take(300).collect();
    let s = TestServer::start(&[]);
    let c = client();
    create(&c, &s, &json!({"session": "qos", "kind": "pose_graph_2d"})).await;
    let z = zenoh_peer(&s.zenoh).await;
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
    let mut subscribers = Vec::new();
    for key in ["factord/qos/out/**", "factord/qos/bin/poses"] {
        let tx = tx.clone();
        let subscriber = z
            .declare_subscriber(key)
            .callback(move |sample| {
                let topic = sample
                    .key_expr()
                    .as_str()
                    .trim_start_matches("factord/qos/");
                let _ = tx.send((
                    topic.to_string(),
                    sample.express(),
                    sample.congestion_control(),
                    sample.encoding().to_string(),
                ));
            })
            .await
            .unwrap();
        subscribers.push(subscriber);
    }
    let publisher = z.declare_publisher("factord/qos/in/batch").await.unwrap();
    zenoh_get(&z, "factord/qos/estimate", None).await.unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    for b in &batches {
        publisher.put(b.to_string()).await.unwrap();
    }
    // A refused batch (an unknown factor type) gets an error event.
    publisher
        .put(json!({"factors": [{"type": "no_such_factor", "keys": [0]}]}).to_string())
        .await
        .unwrap();
    let mut seen: BTreeMap<String, BTreeSet<(bool, String, String)>> = BTreeMap::new();
    while let Ok(Some((topic, express, congestion, encoding))) =
        tokio::time::timeout(Duration::from_secs(2), rx.recv()).await
    {
        seen.entry(topic)
            .or_default()
            .insert((express, format!("{congestion:?}"), encoding));
    }
    let json = "application/json".to_string();
    let at_once = BTreeSet::from([(true, "Block".to_string(), json.clone())]);
    for topic in ["out/acks", "out/poses", "out/summary", "out/errors"] {
        assert_eq!(seen.get(topic), Some(&at_once), "{topic}: {seen:?}");
    }
    let binary = "application/octet-stream".to_string();
    let binary_at_once = BTreeSet::from([(true, "Block".to_string(), binary)]);
    assert_eq!(seen.get("bin/poses"), Some(&binary_at_once), "{seen:?}");
    let batched = BTreeSet::from([(false, "Drop".to_string(), json)]);
    assert_eq!(seen.get("out/stats"), Some(&batched), "{seen:?}");
    drop(subscribers);
    z.close().await.unwrap();
    s.assert_no_panic();
}
