//! Prometheus metrics (`GET /metrics`, text exposition format 0.0.4): process-wide counters and
//! histograms updated where things happen, gauges read from the service when scraped.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::Duration;

/// A fixed-bucket histogram of seconds.
pub struct Histogram {
    bounds: &'static [f64],
    /// Per bucket (non-cumulative), the last one is +Inf.
    counts: [AtomicU64; 16],
    sum_nanos: AtomicU64,
}

impl Histogram {
    const fn new(bounds: &'static [f64]) -> Self {
        assert!(bounds.len() < 16);
        Self {
            bounds,
            counts: [const { AtomicU64::new(0) }; 16],
            sum_nanos: AtomicU64::new(0),
        }
    }

    pub fn observe(&self, d: Duration) {
        let s = d.as_secs_f64();
        let bucket = self
            .bounds
            .iter()
            .position(|&b| s <= b)
            .unwrap_or(self.bounds.len());
        self.counts[bucket].fetch_add(1, Ordering::Relaxed);
        self.sum_nanos
            .fetch_add(d.as_nanos() as u64, Ordering::Relaxed);
    }

    fn render(&self, out: &mut String, name: &str, help: &str) {
        let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} histogram");
        let mut cumulative = 0;
        for (i, &bound) in self.bounds.iter().enumerate() {
            cumulative += self.counts[i].load(Ordering::Relaxed);
            let _ = writeln!(out, "{name}_bucket{{le=\"{bound}\"}} {cumulative}");
        }
        cumulative += self.counts[self.bounds.len()].load(Ordering::Relaxed);
        let _ = writeln!(out, "{name}_bucket{{le=\"+Inf\"}} {cumulative}");
        let sum = self.sum_nanos.load(Ordering::Relaxed) as f64 * 1e-9;
        let _ = writeln!(out, "{name}_sum {sum}\n{name}_count {cumulative}");
    }
}

static SOLVE_SECONDS: Histogram = Histogram::new(&[
    0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 10.0,
]);
static FSYNC_SECONDS: Histogram = Histogram::new(&[
    0.00005, 0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.5,
]);
static SOLVES: AtomicU64 = AtomicU64::new(0);
static ITERATIONS: AtomicU64 = AtomicU64::new(0);
static ACCEPTED_BATCHES: AtomicU64 = AtomicU64::new(0);
static REJECTED: Mutex<BTreeMap<String, u64>> = Mutex::new(BTreeMap::new());

pub fn observe_fsync(d: Duration) {
    if !d.is_zero() {
        FSYNC_SECONDS.observe(d);
    }
}

pub fn observe_solve(d: Duration, iterations: usize) {
    SOLVE_SECONDS.observe(d);
    SOLVES.fetch_add(1, Ordering::Relaxed);
    ITERATIONS.fetch_add(iterations as u64, Ordering::Relaxed);
}

pub fn count_accepted_batch() {
    ACCEPTED_BATCHES.fetch_add(1, Ordering::Relaxed);
}

/// A refused input (any 4xx), by its error code.
pub fn count_rejection(error: &crate::api::error::ErrorBody) {
    // Refusals of what a client sent (4xx); a 503 is the server's state, not bad input.
    if !(400..500).contains(&error.status) {
        return;
    }
    let mut map = REJECTED.lock().unwrap_or_else(|p| p.into_inner());
    *map.entry(error.code.clone()).or_default() += 1;
}

/// The service's state at a scrape (read by the service, which this layer does not see).
pub struct Gauges {
    pub sessions: usize,
    pub sessions_recovering: usize,
    pub queued: usize,
    pub busy_workers: usize,
    pub workers: usize,
    pub session_memory_bytes: usize,
    pub uptime_seconds: f64,
}

pub fn render(g: &Gauges) -> String {
    let mut out = String::new();
    let gauges = [
        ("factord_sessions", "Sessions held", g.sessions as f64),
        (
            "factord_sessions_recovering",
            "Sessions being rebuilt from their journal",
            g.sessions_recovering as f64,
        ),
        (
            "factord_queue_depth",
            "Solves and jobs waiting for a worker",
            g.queued as f64,
        ),
        (
            "factord_busy_workers",
            "Workers running a solve or job",
            g.busy_workers as f64,
        ),
        ("factord_workers", "Worker threads", g.workers as f64),
        (
            "factord_session_memory_bytes",
            "Estimated memory held by all sessions",
            g.session_memory_bytes as f64,
        ),
        (
            "factord_uptime_seconds",
            "Time since start",
            g.uptime_seconds,
        ),
    ];
    for (name, help, value) in gauges {
        let _ = writeln!(
            out,
            "# HELP {name} {help}\n# TYPE {name} gauge\n{name} {value}"
        );
    }
    let counters = [
        (
            "factord_solves_total",
            "Finished session solves",
            SOLVES.load(Ordering::Relaxed),
        ),
        (
            "factord_solver_iterations_total",
            "Solver iterations of session solves",
            ITERATIONS.load(Ordering::Relaxed),
        ),
        (
            "factord_batches_accepted_total",
            "Batches accepted (and journalled)",
            ACCEPTED_BATCHES.load(Ordering::Relaxed),
        ),
    ];
    for (name, help, value) in counters {
        let _ = writeln!(
            out,
            "# HELP {name} {help}\n# TYPE {name} counter\n{name} {value}"
        );
    }
    let _ = writeln!(
        out,
        "# HELP factord_rejected_inputs_total Inputs refused, by error code\n# TYPE factord_rejected_inputs_total counter"
    );
    for (code, n) in REJECTED.lock().unwrap_or_else(|p| p.into_inner()).iter() {
        let _ = writeln!(
            out,
            "factord_rejected_inputs_total{{reason=\"{code}\"}} {n}"
        );
    }
    SOLVE_SECONDS.render(
        &mut out,
        "factord_solve_duration_seconds",
        "Wall time of session solves",
    );
    FSYNC_SECONDS.render(
        &mut out,
        "factord_journal_fsync_seconds",
        "Journal fsync latency",
    );
    out
}
