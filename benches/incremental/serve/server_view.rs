//! The server's side of a stream, to tell where a slow update's time went: every solve's
//! `summary` event (heard over zenoh in both transports) with its engine time, and at the end the
//! server's fsync and solve histograms from `/metrics`.
//!
//! `--dump-server out.jsonl` writes one line per summary: `arrived_ms` (since the stream
//! started, on the client's clock), `sequence`, `solve`, `solve_seconds` and the incremental
//! report's phase times when the solve was an engine update. A client latency far above the
//! engine time of the solve that answered it was spent outside the engine (transport, journal,
//! a solve it queued behind).

use std::sync::{Arc, Mutex};
use std::time::Instant;

use serde_json::{json, Value};

use crate::common::server::zenoh_peer;

/// Summaries as they arrive: (arrival, event).
pub struct ServerView {
    _session: zenoh::Session,
    _subscriber: zenoh::pubsub::Subscriber<()>,
    seen: Arc<Mutex<Vec<(Instant, Value)>>>,
}

impl ServerView {
    pub async fn listen(zenoh: &str, session: &str) -> Self {
        let z = zenoh_peer(zenoh).await;
        let seen: Arc<Mutex<Vec<(Instant, Value)>>> = Default::default();
        let sink = seen.clone();
        let subscriber = z
            .declare_subscriber(format!("factord/{session}/out/summary"))
            .callback(move |sample| {
                let at = Instant::now();
                if let Ok(v) = serde_json::from_slice::<Value>(&sample.payload().to_bytes()) {
                    sink.lock().expect("not poisoned").push((at, v));
                }
            })
            .await
            .expect("summary subscriber");
        Self {
            _session: z,
            _subscriber: subscriber,
            seen,
        }
    }

    /// One JSON object per summary, times relative to `start`.
    pub fn lines(&self, start: Instant) -> String {
        let seen = self.seen.lock().expect("not poisoned");
        let mut out = String::new();
        for (at, v) in seen.iter() {
            let summary = &v["summary"];
            let line = json!({
                "arrived_ms": at.saturating_duration_since(start).as_secs_f64() * 1e3,
                "sequence": v["sequence"],
                "solve": v["solve"],
                "solve_seconds": summary["solve_seconds"],
                "incremental": summary["used"]["incremental"],
            });
            out.push_str(&line.to_string());
            out.push('\n');
        }
        out
    }
}

/// The server's histograms that bear on update latency, from its Prometheus text: bucket
/// upper bound (seconds) → cumulative count, per histogram.
pub fn histograms(metrics: &str) -> Value {
    let mut out = serde_json::Map::new();
    for name in [
        "factord_journal_fsync_seconds",
        "factord_solve_duration_seconds",
        "factord_provisional_answer_seconds",
        "factord_solve_landing_seconds",
    ] {
        let prefix = format!("{name}_bucket{{le=\"");
        let buckets: serde_json::Map<String, Value> = metrics
            .lines()
            .filter_map(|l| l.strip_prefix(&prefix))
            .filter_map(|rest| {
                let (le, count) = rest.split_once("\"} ")?;
                Some((le.to_string(), json!(count.trim().parse::<f64>().ok()?)))
            })
            .collect();
        out.insert(name.to_string(), Value::Object(buckets));
    }
    Value::Object(out)
}
