//! Retrying producers for exactly-once ingest, as a robot would run them: numbered batches
//! (`producer`, `producer_seq` 1, 2, 3, …), every unacknowledged batch kept, progress learned
//! from the cumulative `accepted_through` of any acknowledgement (or a `lagged` marker, or
//! `producer_status`), and everything not acknowledged sent again after a timeout without
//! progress, a lost connection or a restart. Transient refusals (503, 429, connection errors)
//! are retried; any other refusal stops the producer with an error.
//!
//! Every acknowledgement that arrives is also audited ([`Audit`]): a batch acknowledged with
//! another session sequence or other factor ids than the first time (applied twice), or a
//! `duplicate` whose `accepted_through` went back, is a server fault, reported as an error.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use factord::factors::testing::Rng;
use serde_json::{json, Value};
use zenoh::qos::CongestionControl;

/// What a producer did, counted as it goes (read by the test while it runs).
#[derive(Default)]
pub struct Counters {
    /// Highest `accepted_through` learned (the test's progress meter).
    pub accepted_through: AtomicU64,
    /// Every send of a batch (first sends and resends).
    pub sends: AtomicU64,
    /// Sends of a batch sent before.
    pub resends: AtomicU64,
    /// Acknowledgements received with `duplicate: true`.
    pub duplicates: AtomicU64,
    /// Acknowledgements received and ignored on purpose (zenoh).
    pub acks_ignored: AtomicU64,
    /// Transient refusals (503, 429) and connection failures.
    pub transient: AtomicU64,
    /// `producer_status` questions asked.
    pub status_queries: AtomicU64,
    /// Rewinds: sending again from the first unacknowledged batch.
    pub rewinds: AtomicU64,
    /// `lagged` markers received.
    pub lagged: AtomicU64,
}

impl Counters {
    pub fn get(c: &AtomicU64) -> u64 {
        c.load(Ordering::SeqCst)
    }

    fn add(c: &AtomicU64) {
        c.fetch_add(1, Ordering::SeqCst);
    }

    fn advance(&self, through: u64) {
        self.accepted_through.fetch_max(through, Ordering::SeqCst);
    }

    pub fn summary(&self) -> String {
        format!(
            "sends {}, resends {}, duplicates {}, acks ignored {}, transient {}, status queries {}, rewinds {}, lagged {}",
            Self::get(&self.sends),
            Self::get(&self.resends),
            Self::get(&self.duplicates),
            Self::get(&self.acks_ignored),
            Self::get(&self.transient),
            Self::get(&self.status_queries),
            Self::get(&self.rewinds),
            Self::get(&self.lagged),
        )
    }
}

/// Every acknowledgement one producer received, checked as it arrives.
#[derive(Default)]
pub struct Audit {
    /// producer_seq → the session sequence and factor ids of its first acknowledgement.
    first: HashMap<u64, (u64, Vec<u64>)>,
    highest_through: u64,
    /// Acknowledgements not marked `duplicate` whose `accepted_through` is below one seen
    /// before: a restarted server re-publishing the acks of the batches its recovery replays.
    /// They must repeat the original (same session sequence and factor ids).
    pub replayed: Vec<String>,
}

impl Audit {
    /// Checks one acknowledgement of `producer` for a batch of `factors` factors. Errors name
    /// the server fault: a batch given other factor ids or another session sequence than the
    /// first time (applied twice), a `duplicate` whose `accepted_through` went back.
    fn check(&mut self, producer: &str, ack: &Value, factors: usize) -> Result<(), String> {
        let seq = ack["producer_seq"]
            .as_u64()
            .ok_or_else(|| format!("{producer}: an acknowledgement without producer_seq: {ack}"))?;
        let through = ack["accepted_through"].as_u64().ok_or_else(|| {
            format!("{producer}: an acknowledgement without accepted_through: {ack}")
        })?;
        let sequence = ack["sequence"]
            .as_u64()
            .ok_or_else(|| format!("{producer}: an acknowledgement without sequence: {ack}"))?;
        if ack["producer"] != producer {
            return Err(format!(
                "{producer}: an acknowledgement of another producer: {ack}"
            ));
        }
        if through < seq {
            return Err(format!(
                "{producer}: batch {seq} acknowledged with accepted_through {through}: {ack}"
            ));
        }
        let ids: Vec<u64> = ack["factor_ids"]
            .as_array()
            .ok_or_else(|| format!("{producer}: no factor_ids: {ack}"))?
            .iter()
            .map(|v| v.as_u64().unwrap_or(u64::MAX))
            .collect();
        if ids.len() != factors {
            return Err(format!(
                "{producer}: batch {seq} has {factors} factors, its acknowledgement {} ids: {ack}",
                ids.len()
            ));
        }
        let known = self.first.get(&seq);
        if let Some((first_sequence, first_ids)) = known {
            if (*first_sequence, first_ids) != (sequence, &ids) {
                return Err(format!(
                    "{producer}: batch {seq} applied twice: first acknowledged as sequence \
                     {first_sequence} with factor ids {first_ids:?}, now {ack}"
                ));
            }
        }
        // accepted_through is cumulative: it never goes back, but for re-published acks of a
        // replay (checked above against the original when it was seen).
        if through < self.highest_through {
            if ack["duplicate"] == true {
                return Err(format!(
                    "{producer}: accepted_through went back from {} to {through}: {ack}",
                    self.highest_through
                ));
            }
            self.replayed.push(format!(
                "{ack} after accepted_through {}{}",
                self.highest_through,
                if known.is_some() {
                    ""
                } else {
                    " (original not seen)"
                }
            ));
        }
        self.highest_through = self.highest_through.max(through);
        self.first.entry(seq).or_insert((sequence, ids));
        Ok(())
    }

    /// Every factor id acknowledged, each batch once.
    pub fn factor_ids(&self) -> Vec<u64> {
        self.first
            .values()
            .flat_map(|(_, ids)| ids)
            .copied()
            .collect()
    }

    pub fn batches_acknowledged(&self) -> usize {
        self.first.len()
    }
}

/// What every producer needs: who it is, what it sends, where it counts.
pub struct Producer {
    pub session: String,
    pub name: String,
    /// The batches without producer fields; batch k (0-based) is sent as number k + 1.
    pub batches: Vec<Value>,
    pub counters: Arc<Counters>,
    pub audit: Arc<Mutex<Audit>>,
    /// Give up (an error) when nothing is acknowledged for this long.
    pub stall_limit: Duration,
    /// Batches per second, as a robot produces them: batch k is not sent before k / rate
    /// seconds after the start (resends are not paced; a producer behind catches up at once).
    pub rate: f64,
}

impl Producer {
    pub fn new(session: &str, name: &str, batches: Vec<Value>) -> Self {
        Self {
            session: session.into(),
            name: name.into(),
            batches,
            counters: Arc::new(Counters::default()),
            audit: Arc::new(Mutex::new(Audit::default())),
            stall_limit: Duration::from_secs(30),
            rate: f64::INFINITY,
        }
    }

    /// When batch `seq` is due, for a producer started at `start`.
    fn due(&self, start: Instant, seq: u64) -> Instant {
        start + Duration::from_secs_f64((seq - 1) as f64 / self.rate)
    }

    /// Batch `seq` (1-based) with its producer fields.
    fn numbered(&self, seq: u64) -> Value {
        let mut b = self.batches[seq as usize - 1].clone();
        b["producer"] = json!(self.name);
        b["producer_seq"] = json!(seq);
        b
    }

    fn factors_of(&self, seq: u64) -> usize {
        self.batches
            .get(seq as usize - 1)
            .and_then(|b| b["factors"].as_array())
            .map_or(0, Vec::len)
    }

    fn total(&self) -> u64 {
        self.batches.len() as u64
    }

    /// Audits an acknowledgement of this producer; returns its accepted_through.
    fn audit_ack(&self, ack: &Value) -> Result<u64, String> {
        let seq = ack["producer_seq"].as_u64().unwrap_or(0);
        if seq == 0 || seq > self.total() {
            return Err(format!(
                "{}: acknowledgement of an unknown batch: {ack}",
                self.name
            ));
        }
        self.audit
            .lock()
            .unwrap()
            .check(&self.name, ack, self.factors_of(seq))?;
        if ack["duplicate"] == true {
            Counters::add(&self.counters.duplicates);
        }
        Ok(ack["accepted_through"].as_u64().unwrap_or(0))
    }
}

/// Whether an error body (`{"code", "status", …}`) is a transient refusal.
fn transient(error: &Value) -> bool {
    matches!(error["status"].as_u64(), Some(503 | 429))
}

// ---------------------------------------------------------------------------------------------
// HTTP

/// Sends every batch with `POST <base>/v1/sessions/<s>/batches`, one at a time (a batch is sent
/// once the one before is acknowledged: over one request at a time nothing can overtake). A
/// lost answer (connection closed, server killed) is sent again as is: the server answers it
/// with its original acknowledgement (`duplicate`). After a few failures in a row (the server
/// is probably down) it asks `GET …/producers/<p>` where to resume instead.
pub async fn run_http(p: Arc<Producer>, base: String) -> Result<(), String> {
    let client = reqwest::Client::builder()
        .pool_max_idle_per_host(0)
        .timeout(Duration::from_secs(10))
        .build()
        .expect("client");
    let url = format!("{base}/v1/sessions/{}/batches", p.session);
    let status_url = format!("{base}/v1/sessions/{}/producers/{}", p.session, p.name);
    let mut next = 1u64;
    let mut highest_sent = 0u64;
    let mut failures = 0u32;
    let mut last_progress = Instant::now();
    let start = Instant::now();
    while next <= p.total() {
        if next > highest_sent {
            tokio::time::sleep_until(p.due(start, next).into()).await;
        }
        if last_progress.elapsed() > p.stall_limit {
            return Err(format!(
                "{}: no progress for {:?} at batch {next}",
                p.name, p.stall_limit
            ));
        }
        if failures >= 3 {
            Counters::add(&p.counters.status_queries);
            if let Some(through) = http_status(&client, &status_url).await? {
                p.counters.advance(through);
                if through + 1 > next {
                    next = through + 1;
                    last_progress = Instant::now();
                }
                failures = 0;
                continue;
            }
        }
        Counters::add(&p.counters.sends);
        if next <= highest_sent {
            Counters::add(&p.counters.resends);
        }
        highest_sent = highest_sent.max(next);
        let sent = client
            .post(&url)
            .header("content-type", "application/json")
            .header("connection", "close")
            .body(p.numbered(next).to_string())
            .send()
            .await;
        let (status, retry_after, text) = match sent {
            Ok(r) => {
                let status = r.status().as_u16();
                let retry_after = r
                    .headers()
                    .get("retry-after")
                    .and_then(|v| v.to_str().ok()?.parse::<u64>().ok());
                match r.text().await {
                    Ok(text) => (status, retry_after, text),
                    Err(_) => (0, None, String::new()),
                }
            }
            Err(_) => (0, None, String::new()),
        };
        let body: Value = serde_json::from_str(&text).unwrap_or(Value::String(text));
        match status {
            200 => {
                let through = p.audit_ack(&body)?;
                if body["producer_seq"] != next {
                    return Err(format!("{}: sent {next}, acknowledged {body}", p.name));
                }
                p.counters.advance(through);
                next = through + 1;
                failures = 0;
                last_progress = Instant::now();
            }
            // The connection was lost (killed server, closed by the proxy, no server yet).
            0 => {
                Counters::add(&p.counters.transient);
                failures += 1;
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            503 | 429 => {
                Counters::add(&p.counters.transient);
                failures += 1;
                let wait = retry_after.map_or(50, |s| (s * 1000).min(500));
                tokio::time::sleep(Duration::from_millis(wait)).await;
            }
            _ => {
                return Err(format!(
                    "{}: batch {next} refused with {status}: {body}",
                    p.name
                ))
            }
        }
    }
    Ok(())
}

/// `accepted_through` from `GET …/producers/<p>`; `None` when the server does not answer now.
async fn http_status(client: &reqwest::Client, url: &str) -> Result<Option<u64>, String> {
    let Ok(r) = client.get(url).header("connection", "close").send().await else {
        return Ok(None);
    };
    let status = r.status().as_u16();
    let Ok(body) = r.json::<Value>().await else {
        return Ok(None);
    };
    match status {
        200 => Ok(body["accepted_through"].as_u64()),
        503 | 429 => Ok(None),
        _ => Err(format!("{url}: {status} {body}")),
    }
}

// ---------------------------------------------------------------------------------------------
// zenoh

/// Faults a zenoh producer makes on purpose.
pub struct ZenohFaults {
    /// Share of received acknowledgements ignored (as if lost).
    pub ignore_acks: f64,
    pub seed: u64,
}

/// How many batches may be published beyond the last acknowledged one.
const WINDOW: u64 = 48;
/// Without progress for this long, everything unacknowledged is sent again.
const RESEND_AFTER: Duration = Duration::from_millis(600);

/// Publishes every batch on `<prefix>/<s>/in/batch` (reliable by default, blocking under congestion), at
/// most [`WINDOW`] beyond the acknowledged ones, and learns progress from `out/acks`,
/// `out/lagged` and `out/errors`. A gap refusal (puts lost while the server restarted) or a
/// transient refusal sends everything unacknowledged again; so does a timeout without
/// progress, after asking `producer_status` over `<prefix>/rpc` when the server answers.
pub async fn run_zenoh(
    p: Arc<Producer>,
    z: zenoh::Session,
    prefix: &str,
    faults: ZenohFaults,
) -> Result<(), String> {
    let out = format!("{prefix}/{}/out", p.session);
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel::<(String, Value)>();
    let mut subscribers = Vec::new();
    for topic in ["acks", "errors", "lagged"] {
        let tx = tx.clone();
        let sub = z
            .declare_subscriber(format!("{out}/{topic}"))
            .callback(move |sample| {
                let key = sample.key_expr().as_str().to_string();
                let v = serde_json::from_slice(&sample.payload().to_bytes())
                    .unwrap_or_else(|e| json!({"unparsed": e.to_string()}));
                let _ = tx.send((key, v));
            })
            .await
            .map_err(|e| format!("subscribe: {e}"))?;
        subscribers.push(sub);
    }
    let publisher = z
        .declare_publisher(format!("{prefix}/{}/in/batch", p.session))
        .congestion_control(CongestionControl::Block)
        .await
        .map_err(|e| format!("publisher: {e}"))?;
    let mut rng = Rng::new(faults.seed);
    let mut acked = 0u64;
    let mut next = 1u64;
    let mut highest_sent = 0u64;
    let mut last_progress = Instant::now();
    let mut last_rewind = Instant::now() - RESEND_AFTER;
    let mut stalled_since = Instant::now();
    let start = Instant::now();
    while acked < p.total() {
        if stalled_since.elapsed() > p.stall_limit {
            return Err(format!(
                "{}: nothing acknowledged for {:?} (through {acked})",
                p.name, p.stall_limit
            ));
        }
        while next <= p.total() && next <= acked + WINDOW {
            if next > highest_sent && p.due(start, next) > Instant::now() {
                break;
            }
            Counters::add(&p.counters.sends);
            if next <= highest_sent {
                Counters::add(&p.counters.resends);
            }
            highest_sent = highest_sent.max(next);
            publisher
                .put(p.numbered(next).to_string())
                .await
                .map_err(|e| format!("put: {e}"))?;
            next += 1;
        }
        let mut wait = RESEND_AFTER.saturating_sub(last_progress.elapsed());
        if next <= p.total() && next <= acked + WINDOW && next > highest_sent {
            wait = wait.min(p.due(start, next).saturating_duration_since(Instant::now()));
        }
        let event = tokio::time::timeout(wait, rx.recv()).await;
        let mut rewind = false;
        match event {
            Ok(Some((key, v))) => {
                let before = acked;
                match v["type"].as_str() {
                    Some("ack") if v["producer"] == p.name.as_str() => {
                        let through = p.audit_ack(&v)?;
                        if rng.uniform() < faults.ignore_acks {
                            Counters::add(&p.counters.acks_ignored);
                        } else {
                            acked = acked.max(through);
                        }
                    }
                    Some("lagged") => {
                        Counters::add(&p.counters.lagged);
                        if let Some(through) = v["producers"][p.name.as_str()].as_u64() {
                            acked = acked.max(through);
                        }
                    }
                    Some("error") => {
                        let error = &v["error"];
                        let ours = v["producer"] == p.name.as_str();
                        if !(ours || v.get("producer").is_none()) {
                            continue; // another producer's refusal
                        }
                        if transient(error) {
                            Counters::add(&p.counters.transient);
                            rewind = true;
                        } else if ours && error["code"] == "producer_sequence_gap" {
                            rewind = true;
                        } else {
                            return Err(format!("{}: refused on {key}: {v}", p.name));
                        }
                    }
                    _ => {}
                }
                if acked > before {
                    p.counters.advance(acked);
                    last_progress = Instant::now();
                    stalled_since = Instant::now();
                    next = next.max(acked + 1);
                }
            }
            Ok(None) => return Err(format!("{}: subscriptions closed", p.name)),
            // The next batch is due.
            Err(_) if last_progress.elapsed() < RESEND_AFTER => {}
            Err(_) => {
                // No progress for RESEND_AFTER: ask where the server is, then send again.
                Counters::add(&p.counters.status_queries);
                if let Some(through) = zenoh_status(&z, prefix, &p.session, &p.name).await? {
                    if through > acked {
                        acked = through;
                        p.counters.advance(acked);
                        stalled_since = Instant::now();
                    }
                }
                last_progress = Instant::now();
                rewind = true;
                last_rewind = Instant::now() - RESEND_AFTER;
            }
        }
        // Rewinds at most every 200 ms: the refusals of one burst of lost puts arrive together.
        if rewind && last_rewind.elapsed() > Duration::from_millis(200) && next > acked + 1 {
            Counters::add(&p.counters.rewinds);
            next = acked + 1;
            last_rewind = Instant::now();
        }
    }
    drop(subscribers);
    Ok(())
}

/// `producer_status` over `<prefix>/rpc`; `None` when no server answers within 300 ms.
async fn zenoh_status(
    z: &zenoh::Session,
    prefix: &str,
    session: &str,
    producer: &str,
) -> Result<Option<u64>, String> {
    let command = json!({"op": "producer_status", "session": session, "producer": producer});
    let replies = z
        .get(format!("{prefix}/rpc"))
        .payload(command.to_string())
        .timeout(Duration::from_millis(300))
        .await
        .map_err(|e| format!("query: {e}"))?;
    let Ok(reply) = replies.recv_async().await else {
        return Ok(None);
    };
    match reply.result() {
        Ok(sample) => {
            let v: Value = serde_json::from_slice(&sample.payload().to_bytes())
                .map_err(|e| format!("producer_status reply: {e}"))?;
            Ok(v["accepted_through"].as_u64())
        }
        Err(err) => {
            let v: Value = serde_json::from_slice(&err.payload().to_bytes()).unwrap_or_default();
            if transient(&v["error"]) {
                Ok(None)
            } else {
                Err(format!("producer_status refused: {v}"))
            }
        }
    }
}
