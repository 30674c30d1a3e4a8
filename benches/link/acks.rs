//! What one producer's subscriber of `factord/<s>/out/**` learns: which of its batches are
//! acknowledged, individually (an ack naming its `producer_seq`) or only cumulatively (a later
//! ack's `accepted_through`, or a `lagged` marker's `producers`), and when: the latency of a
//! batch is from its first send to the first event that covers it.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use serde::Deserialize;

/// The fields of an event this bench reads (the rest is skipped unparsed).
#[derive(Deserialize)]
struct Event {
    #[serde(rename = "type")]
    kind: String,
    producer: Option<String>,
    producer_seq: Option<u64>,
    accepted_through: Option<u64>,
    producers: Option<BTreeMap<String, u64>>,
    duplicate: Option<bool>,
    error: Option<ErrorBody>,
}

#[derive(Deserialize, Default)]
struct ErrorBody {
    code: Option<String>,
    message: Option<String>,
}

#[derive(Default)]
pub struct Tracker {
    producer: String,
    /// Per batch (producer_seq − 1): first send, covered at, acked individually.
    sent: Vec<Option<Instant>>,
    covered_at: Vec<Option<Instant>>,
    individually: Vec<bool>,
    /// Every batch up to here is covered.
    frontier: u64,
    pub covered: u64,
    pub duplicates: u64,
    /// Lagged markers seen, by key.
    pub lagged: BTreeMap<String, u64>,
    /// Error events for this producer (code: message), and how many.
    pub errors: Vec<String>,
    pub events: u64,
}

pub type Shared = Arc<Mutex<Tracker>>;

impl Tracker {
    pub fn new(producer: &str, batches: usize) -> Shared {
        Arc::new(Mutex::new(Self {
            producer: producer.to_string(),
            sent: vec![None; batches],
            covered_at: vec![None; batches],
            individually: vec![false; batches],
            ..Self::default()
        }))
    }

    /// Notes the first send of batch `seq` (1-based); later sends keep the first time.
    pub fn sending(&mut self, seq: u64) {
        let slot = &mut self.sent[seq as usize - 1];
        slot.get_or_insert_with(Instant::now);
    }

    /// An event arrived on `key` at `at`.
    pub fn take(&mut self, key: &str, payload: &[u8], at: Instant) {
        self.events += 1;
        let Ok(e) = serde_json::from_slice::<Event>(payload) else {
            return;
        };
        let mine = e.producer.as_deref() == Some(self.producer.as_str());
        if e.duplicate == Some(true) {
            self.duplicates += 1;
        }
        match e.kind.as_str() {
            "ack" if mine => {
                let seq = e.producer_seq.unwrap_or(0);
                if seq >= 1 && seq as usize <= self.sent.len() {
                    self.individually[seq as usize - 1] = true;
                    self.cover(seq, at);
                }
                self.cover_through(e.accepted_through.unwrap_or(0), at);
            }
            "ack" => {}
            "lagged" => {
                *self.lagged.entry(key.to_string()).or_default() += 1;
                let through = e
                    .producers
                    .as_ref()
                    .and_then(|p| p.get(&self.producer).copied());
                self.cover_through(through.unwrap_or(0), at);
            }
            "error" if mine || e.producer.is_none() => {
                let body = e.error.unwrap_or_default();
                self.errors.push(format!(
                    "{} (batch {:?}): {}",
                    body.code.unwrap_or_default(),
                    e.producer_seq,
                    body.message.unwrap_or_default()
                ))
            }
            _ => {}
        }
    }

    fn cover(&mut self, seq: u64, at: Instant) {
        let i = seq as usize - 1;
        if self.covered_at[i].is_none() {
            self.covered_at[i] = Some(at);
            self.covered += 1;
        }
    }

    fn cover_through(&mut self, through: u64, at: Instant) {
        let through = through.min(self.sent.len() as u64);
        while self.frontier < through {
            self.frontier += 1;
            self.cover(self.frontier, at);
        }
    }

    /// The highest number up to which every batch is covered.
    pub fn frontier(&self) -> u64 {
        // Individual acks may have covered batches beyond the cumulative frontier.
        let mut f = self.frontier;
        while (f as usize) < self.covered_at.len() && self.covered_at[f as usize].is_some() {
            f += 1;
        }
        f
    }

    /// Latencies (ms) of the covered batches, in producer order.
    pub fn latencies_ms(&self) -> Vec<f64> {
        self.sent
            .iter()
            .zip(&self.covered_at)
            .filter_map(|(s, c)| Some(c.as_ref()?.saturating_duration_since(*s.as_ref()?)))
            .map(|d| d.as_secs_f64() * 1e3)
            .collect()
    }

    /// (first send, latency in ms) of the covered batches.
    pub fn timed_latencies_ms(&self) -> Vec<(Instant, f64)> {
        self.sent
            .iter()
            .zip(&self.covered_at)
            .filter_map(|(s, c)| {
                let s = *s.as_ref()?;
                Some((
                    s,
                    c.as_ref()?.saturating_duration_since(s).as_secs_f64() * 1e3,
                ))
            })
            .collect()
    }

    /// (acked individually, covered only cumulatively).
    pub fn split(&self) -> (u64, u64) {
        let individually = self.individually.iter().filter(|&&b| b).count() as u64;
        (individually, self.covered - individually.min(self.covered))
    }

    pub fn lagged_total(&self) -> u64 {
        self.lagged.values().sum()
    }
}

/// Subscribes `tracker` to `key` (e.g. `factord/<s>/out/**`), timestamping at arrival.
pub async fn subscribe(
    z: &zenoh::Session,
    key: &str,
    tracker: Shared,
    wake: Arc<tokio::sync::Notify>,
) -> zenoh::pubsub::Subscriber<()> {
    z.declare_subscriber(key)
        .callback(move |sample| {
            let at = Instant::now();
            let payload = sample.payload().to_bytes();
            tracker
                .lock()
                .expect("not poisoned")
                .take(sample.key_expr().as_str(), &payload, at);
            wake.notify_waiters();
        })
        .await
        .expect("subscriber")
}

/// p-quantile (nearest rank on the sorted values); NaN when empty.
pub fn quantile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((sorted.len() as f64 - 1.0) * p).round() as usize]
}

/// p50, p99 and worst of `values` (ms), sorted in place.
pub fn summary(values: &mut [f64]) -> (f64, f64, f64) {
    values.sort_by(f64::total_cmp);
    (
        quantile(values, 0.5),
        quantile(values, 0.99),
        values.last().copied().unwrap_or(f64::NAN),
    )
}
