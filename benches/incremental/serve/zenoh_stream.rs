//! The stream over zenoh, as a robot publishes: each pose's batch on `<p>/<s>/in/batch`, the
//! next once the previous one's estimate is available, i.e. its ack on `out/acks` says
//! `reflected` or a `summary` event of a solve that includes it arrives on `out/summary`.
//! Like a robot, it also subscribes to its poses, on `out/poses` (JSON) or `bin/poses` (binary),
//! so the server serialises and sends every estimate it would send a robot. (It does not parse
//! them: what a robot spends reading its poses depends on the robot.)

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde_json::{json, Value};

use crate::common::server::{zenoh_get, zenoh_peer, TestServer};
use crate::Streamed;

/// Which of its poses the client subscribes to.
#[derive(Clone, Copy, PartialEq, Debug)]
pub enum Poses {
    Json,
    Binary,
    None,
}

impl Poses {
    pub fn name(self) -> &'static str {
        match self {
            Poses::Json => "json",
            Poses::Binary => "binary",
            Poses::None => "none",
        }
    }
}

/// What a subscriber saw: (arrival, sequence, reflected) per event, and a wake-up.
#[derive(Default)]
struct Seen {
    list: Mutex<Vec<(Instant, u64, bool)>>,
    arrived: tokio::sync::Notify,
}

async fn subscribe(
    z: &zenoh::Session,
    key: &str,
    seen: Arc<Seen>,
) -> zenoh::pubsub::Subscriber<()> {
    z.declare_subscriber(key)
        .callback(move |sample| {
            let at = Instant::now();
            let bytes = sample.payload().to_bytes();
            // A binary estimate's sequence is in its header (proto/v1/poses-binary.md): read
            // as a robot would, without decoding the poses.
            let (sequence, reflected) = match bytes.get(..16) {
                Some(header) if header.starts_with(b"FDPB") => {
                    let sequence: [u8; 8] = header[8..16].try_into().expect("8 bytes");
                    (u64::from_le_bytes(sequence), false)
                }
                _ => {
                    let v: Value = serde_json::from_slice(&bytes).expect("events are JSON");
                    (v["sequence"].as_u64().unwrap_or(0), v["reflected"] == true)
                }
            };
            seen.list
                .lock()
                .expect("not poisoned")
                .push((at, sequence, reflected));
            seen.arrived.notify_waiters();
        })
        .await
        .expect("subscriber")
}

/// The arrival time of the first event in `seen` (from `from` on) that makes `sequence`
/// available: an ack of it with `reflected` (acks) or any summary at or after it.
fn available(seen: &Seen, from: &mut usize, sequence: u64, ack: bool) -> Option<Instant> {
    let list = seen.list.lock().expect("not poisoned");
    let found = list[*from..].iter().find(|(_, s, reflected)| {
        if ack {
            *s == sequence && *reflected
        } else {
            *s >= sequence
        }
    });
    *from = list.len();
    found.map(|(t, _, _)| *t)
}

/// Streams `bodies` into `session` (created beforehand; `base` is its sequence before the
/// first batch). Latency: from `put` to the arrival of the event that makes the estimate
/// available. When no such event arrives within 5 s (an event stream that lagged), the
/// session's `solved_sequence` is asked over the rpc and its answer time is used (`fallbacks`).
/// `budget`: the session has a latency budget, so an estimate of the batch or a later one (a
/// provisional answer) on `bin/poses` makes it available too.
pub async fn stream(
    s: &TestServer,
    session: &str,
    base: u64,
    bodies: &[String],
    poses: Poses,
    budget: bool,
) -> Streamed {
    let z = zenoh_peer(&s.zenoh).await;
    let acks: Arc<Seen> = Default::default();
    let summaries: Arc<Seen> = Default::default();
    let estimates: Arc<Seen> = Default::default();
    let _a = subscribe(&z, &format!("factord/{session}/out/acks"), acks.clone()).await;
    let _e = match budget {
        true => Some(
            subscribe(
                &z,
                &format!("factord/{session}/bin/poses"),
                estimates.clone(),
            )
            .await,
        ),
        false => None,
    };
    let poses_key = match poses {
        Poses::Json => Some(format!("factord/{session}/out/poses")),
        Poses::Binary => Some(format!("factord/{session}/bin/poses")),
        Poses::None => None,
    };
    // Bytes and samples received on the poses key.
    let received = Arc::new((AtomicU64::new(0), AtomicU64::new(0)));
    let poses_subscriber = match poses_key {
        Some(key) => {
            let counts = Arc::clone(&received);
            Some(
                z.declare_subscriber(key)
                    .callback(move |sample| {
                        counts
                            .0
                            .fetch_add(sample.payload().len() as u64, Ordering::Relaxed);
                        counts.1.fetch_add(1, Ordering::Relaxed);
                    })
                    .await
                    .expect("poses subscriber"),
            )
        }
        None => None,
    };
    let _s = subscribe(
        &z,
        &format!("factord/{session}/out/summary"),
        summaries.clone(),
    )
    .await;
    // The rpc answering means the server's peer knows ours; give the subscriptions a moment
    // to propagate as the other zenoh benches do.
    zenoh_get(&z, "factord/rpc", Some(&json!({"op": "health"})))
        .await
        .expect("rpc answers");
    tokio::time::sleep(Duration::from_millis(300)).await;
    let publisher = z
        .declare_publisher(format!("factord/{session}/in/batch"))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .expect("publisher");
    let (mut ack_from, mut summary_from, mut estimate_from) = (0, 0, 0);
    let mut latencies_ms = Vec::with_capacity(bodies.len());
    let mut fallbacks = 0;
    let start = Instant::now();
    for (i, body) in bodies.iter().enumerate() {
        let sequence = base + i as u64 + 1;
        let t = Instant::now();
        publisher.put(body.clone()).await.expect("published");
        let deadline = Instant::now() + Duration::from_secs(5);
        let at = loop {
            // Register for wake-ups before looking, so no arrival is missed in between.
            let (ack_arrived, summary_arrived, estimate_arrived) = (
                acks.arrived.notified(),
                summaries.arrived.notified(),
                estimates.arrived.notified(),
            );
            let got = available(&acks, &mut ack_from, sequence, true)
                .or_else(|| available(&summaries, &mut summary_from, sequence, false))
                .or_else(|| available(&estimates, &mut estimate_from, sequence, false));
            if let Some(at) = got {
                break at;
            }
            if Instant::now() > deadline {
                let stats = zenoh_get(
                    &z,
                    "factord/rpc",
                    Some(&json!({"op": "get_stats", "session": session})),
                )
                .await
                .expect("stats");
                if stats["solved_sequence"].as_u64().unwrap_or(0) >= sequence {
                    fallbacks += 1;
                    break Instant::now();
                }
                assert!(
                    t.elapsed() < Duration::from_secs(300),
                    "pose {i}: no estimate: {stats}"
                );
            }
            let _ = tokio::time::timeout(Duration::from_millis(50), async {
                tokio::select! {
                    _ = ack_arrived => {},
                    _ = summary_arrived => {},
                    _ = estimate_arrived => {},
                }
            })
            .await;
        };
        latencies_ms.push(at.saturating_duration_since(t).as_secs_f64() * 1e3);
    }
    let wall_seconds = start.elapsed().as_secs_f64();
    z.close().await.expect("zenoh closes");
    Streamed {
        latencies_ms,
        wall_seconds,
        fallbacks,
        poses_received: poses_subscriber.is_some().then(|| {
            (
                received.0.load(Ordering::Relaxed),
                received.1.load(Ordering::Relaxed),
            )
        }),
        memory: Vec::new(),
    }
}
