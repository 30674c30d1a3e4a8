//! Prometheus metrics (`GET /metrics`, text exposition format 0.0.4): counters and histograms
//! recorded through the `metrics` facade where things happen, the service's gauges set when
//! scraped, `process_*` metrics (CPU, memory, open files, start time) from `metrics-process`, and
//! `factord_build_info`. `metrics-exporter-prometheus` keeps them and writes the text; it serves
//! nothing itself (the HTTP transport answers `GET /metrics` with [`render`]).
//!
//! The recorder is process-global: it is installed once, by the first call here, so any number
//! of services in one process share it (as they shared the statics this replaced).

use std::sync::{Mutex, OnceLock, PoisonError};
use std::time::{Duration, Instant};

use metrics::{counter, describe_counter, describe_gauge, describe_histogram, gauge, histogram};
use metrics_exporter_prometheus::{Matcher, PrometheusBuilder, PrometheusHandle};

const SOLVE_SECONDS: &str = "factord_solve_duration_seconds";
const FSYNC_SECONDS: &str = "factord_journal_fsync_seconds";
/// Sessions with a latency budget (`session::provisional`): how long a provisional answer
/// took (from its batch's arrival or a landing to its publication), and how long an exact
/// solve's landing held the session (publishing its correction, taking in the batches that
/// waited), which delays provisional answers and batches meanwhile.
const PROVISIONAL_SECONDS: &str = "factord_provisional_answer_seconds";
const LANDING_SECONDS: &str = "factord_solve_landing_seconds";
const SLOW_FSYNCS: &str = "factord_journal_slow_fsyncs_total";
const SOLVES: &str = "factord_solves_total";
const ITERATIONS: &str = "factord_solver_iterations_total";
const ACCEPTED_BATCHES: &str = "factord_batches_accepted_total";
const AUTH_FAILURES: &str = "factord_http_auth_failures_total";
const REJECTED: &str = "factord_rejected_inputs_total";
const REJECTED_HELP: &str = "Inputs refused, by error code";
const BUILD_INFO: &str = "factord_build_info";
const TYPE_COMPILES: &str = "factord_factor_type_compiles_total";
const TYPE_REUSES: &str = "factord_factor_type_reuses_total";
const GROUP_FSYNCS: &str = "factord_journal_group_fsyncs_total";
const GROUP_RECORDS: &str = "factord_journal_group_fsynced_records_total";

/// Upper bounds of the histograms' buckets, in seconds.
const SOLVE_BUCKETS: &[f64] = &[
    0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 10.0,
];
const FSYNC_BUCKETS: &[f64] = &[
    0.00005, 0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.5,
];

/// An fsync at least this long is counted and logged: with fsync always, it holds the answer
/// of the batch it made durable (sphere2500 over HTTP: fsyncs of 0.1–0.5 s, now and then, on
/// this project's test VM, and answers that late while their solves took 11–27 ms).
const SLOW_FSYNC: Duration = Duration::from_millis(50);
/// At most one warning per this long; the next says how many slow fsyncs it stands for.
const SLOW_FSYNC_WARN_EVERY: Duration = Duration::from_secs(10);

/// The service's gauges: name, help.
const GAUGES: [(&str, &str); 9] = [
    ("factord_sessions", "Sessions held"),
    (
        "factord_sessions_recovering",
        "Sessions being rebuilt from their journal",
    ),
    (
        "factord_queue_depth",
        "Solves and jobs waiting for a worker",
    ),
    ("factord_busy_workers", "Workers running a solve or job"),
    ("factord_workers", "Worker threads"),
    (
        "factord_session_memory_bytes",
        "Estimated memory held by all sessions (a factor type several share counted once)",
    ),
    (
        "factord_factor_types",
        "Distinct compiled factor types held (identical definitions share one)",
    ),
    (
        "factord_factor_type_bytes",
        "Estimated memory of the distinct compiled factor types",
    ),
    ("factord_uptime_seconds", "Time since start"),
];

/// How often recorded histogram samples are folded into their buckets between scrapes (the
/// facade queues samples until then; without a scraper the queue would grow).
const UPKEEP_EVERY: Duration = Duration::from_secs(5);

struct Exporter {
    handle: PrometheusHandle,
    process: metrics_process::Collector,
    /// Gauges are set and rendered under this lock, so two services scraped at once each
    /// render their own values.
    scrape: Mutex<()>,
}

fn exporter() -> &'static Exporter {
    static EXPORTER: OnceLock<Exporter> = OnceLock::new();
    EXPORTER.get_or_init(install)
}

fn install() -> Exporter {
    let recorder = PrometheusBuilder::new()
        .set_buckets_for_metric(Matcher::Full(SOLVE_SECONDS.into()), SOLVE_BUCKETS)
        .and_then(|b| b.set_buckets_for_metric(Matcher::Full(FSYNC_SECONDS.into()), FSYNC_BUCKETS))
        .and_then(|b| {
            b.set_buckets_for_metric(Matcher::Full(PROVISIONAL_SECONDS.into()), FSYNC_BUCKETS)
        })
        .and_then(|b| {
            b.set_buckets_for_metric(Matcher::Full(LANDING_SECONDS.into()), FSYNC_BUCKETS)
        })
        .expect("bucket lists are not empty")
        .build_recorder();
    let handle = recorder.handle();
    if let Err(e) = metrics::set_global_recorder(recorder) {
        // Only an embedding program can have done this; its recorder then gets what we record.
        tracing::warn!("metrics: another recorder is installed, /metrics shows none of ours: {e}");
    }
    let upkeep = handle.clone();
    let spawned = std::thread::Builder::new()
        .name("factord-metrics".into())
        .spawn(move || loop {
            std::thread::sleep(UPKEEP_EVERY);
            upkeep.run_upkeep();
        });
    if let Err(e) = spawned {
        tracing::warn!("metrics: no upkeep thread ({e}); histograms are folded at each scrape");
    }
    describe();
    let process = metrics_process::Collector::default();
    process.describe();
    Exporter {
        handle,
        process,
        scrape: Mutex::new(()),
    }
}

/// Help texts, and every metric registered so that a scrape lists it before its first event.
fn describe() {
    for (name, help) in GAUGES {
        describe_gauge!(name, help);
        gauge!(name).set(0.0);
    }
    for (name, help) in [
        (SOLVES, "Finished session solves"),
        (ITERATIONS, "Solver iterations of session solves"),
        (ACCEPTED_BATCHES, "Batches accepted (and journalled)"),
        (
            AUTH_FAILURES,
            "HTTP requests with a wrong bearer token, and failed logins",
        ),
        (
            SLOW_FSYNCS,
            "Journal fsyncs of 50 ms or more (a disk holding answers)",
        ),
        (TYPE_COMPILES, "Factor type definitions compiled"),
        (
            TYPE_REUSES,
            "Factor type declarations served with a type already compiled",
        ),
        (
            GROUP_FSYNCS,
            "Journal fdatasyncs under fsync always (one per group of records, group commit)",
        ),
        (
            GROUP_RECORDS,
            "Journal records those fdatasyncs made durable (divided by the fdatasyncs: records per fsync)",
        ),
    ] {
        describe_counter!(name, help);
        counter!(name).absolute(0);
    }
    describe_counter!(REJECTED, REJECTED_HELP);
    describe_histogram!(SOLVE_SECONDS, "Wall time of session solves");
    describe_histogram!(FSYNC_SECONDS, "Journal fsync latency");
    let _ = histogram!(SOLVE_SECONDS);
    let _ = histogram!(FSYNC_SECONDS);
    describe_histogram!(
        PROVISIONAL_SECONDS,
        "Provisional answers of sessions with a latency budget: from the batch's arrival (or the exact solve's landing) to publication"
    );
    describe_histogram!(
        LANDING_SECONDS,
        "How long an exact solve's landing holds its session (its correction published, waiting batches taken in)"
    );
    describe_gauge!(BUILD_INFO, "The running build: its version, always 1");
    gauge!(BUILD_INFO, "version" => env!("CARGO_PKG_VERSION")).set(1.0);
}

pub fn observe_fsync(d: Duration) {
    exporter();
    if !d.is_zero() {
        histogram!(FSYNC_SECONDS).record(d);
    }
    if d >= SLOW_FSYNC {
        counter!(SLOW_FSYNCS).increment(1);
        warn_slow_fsync(d);
    }
}

/// Logs a slow fsync, at most once per [`SLOW_FSYNC_WARN_EVERY`]: a disk that stalls on every
/// fsync would otherwise write a line per batch.
fn warn_slow_fsync(d: Duration) {
    /// When the last warning was written, and the slow fsyncs since then.
    static LAST: Mutex<Option<(Instant, u64)>> = Mutex::new(None);
    let mut last = LAST.lock().unwrap_or_else(PoisonError::into_inner);
    match &mut *last {
        Some((at, unreported)) if at.elapsed() < SLOW_FSYNC_WARN_EVERY => *unreported += 1,
        _ => {
            let unreported = last.map_or(0, |(_, n)| n);
            tracing::warn!(
                seconds = d.as_secs_f64(),
                slow_since_last_warning = unreported,
                "journal fsync took {d:?}: answers waiting on it are that late (the disk, not the \
                 solver; see {SLOW_FSYNCS})"
            );
            *last = Some((Instant::now(), 0));
        }
    }
}

pub fn observe_solve(d: Duration, iterations: usize) {
    exporter();
    histogram!(SOLVE_SECONDS).record(d);
    counter!(SOLVES).increment(1);
    counter!(ITERATIONS).increment(iterations as u64);
}

pub fn observe_provisional_answer(d: Duration) {
    exporter();
    histogram!(PROVISIONAL_SECONDS).record(d);
}

pub fn observe_landing(d: Duration) {
    exporter();
    histogram!(LANDING_SECONDS).record(d);
}

pub fn count_accepted_batch() {
    exporter();
    counter!(ACCEPTED_BATCHES).increment(1);
}

/// A wrong bearer token or login over HTTP (throttled per peer: see `transport::http::throttle`).
pub fn count_auth_failure() {
    exporter();
    counter!(AUTH_FAILURES).increment(1);
}

/// A refused input (any 4xx), by its error code.
pub fn count_rejection(error: &crate::api::error::ErrorBody) {
    // Refusals of what a client sent (4xx); a 503 is the server's state, not bad input.
    if !(400..500).contains(&error.status) {
        return;
    }
    exporter();
    counter!(REJECTED, "reason" => error.code.clone()).increment(1);
}

/// The service's state at a scrape (read by the service, which this layer does not see).
pub struct Gauges {
    pub sessions: usize,
    pub sessions_recovering: usize,
    pub queued: usize,
    pub busy_workers: usize,
    pub workers: usize,
    pub session_memory_bytes: usize,
    pub factor_types: usize,
    pub factor_type_bytes: usize,
    pub factor_type_compiles: u64,
    pub factor_type_reuses: u64,
    pub uptime_seconds: f64,
}

/// The exposition text: `g` and the process's metrics as of now, the counters and histograms
/// since the process started.
pub fn render(g: &Gauges) -> String {
    let exporter = exporter();
    let _scrape = exporter
        .scrape
        .lock()
        .unwrap_or_else(PoisonError::into_inner);
    let values = [
        g.sessions as f64,
        g.sessions_recovering as f64,
        g.queued as f64,
        g.busy_workers as f64,
        g.workers as f64,
        g.session_memory_bytes as f64,
        g.factor_types as f64,
        g.factor_type_bytes as f64,
        g.uptime_seconds,
    ];
    for ((name, _), value) in GAUGES.iter().zip(values) {
        gauge!(*name).set(value);
    }
    // Kept by the service's interner; absolute, like the gauges, as of this scrape.
    counter!(TYPE_COMPILES).absolute(g.factor_type_compiles);
    counter!(TYPE_REUSES).absolute(g.factor_type_reuses);
    let (fsyncs, records) = crate::journal::group_commit::totals();
    counter!(GROUP_FSYNCS).absolute(fsyncs);
    counter!(GROUP_RECORDS).absolute(records);
    exporter.process.collect();
    let mut text = exporter.handle.render();
    // The exporter lists a labelled counter from its first sample; this one is documented (and
    // typed) before any input was refused.
    if !text.contains(&format!("# TYPE {REJECTED} ")) {
        text.push_str(&format!(
            "# HELP {REJECTED} {REJECTED_HELP}\n# TYPE {REJECTED} counter\n"
        ));
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gauges() -> Gauges {
        Gauges {
            sessions: 3,
            sessions_recovering: 1,
            queued: 0,
            busy_workers: 2,
            workers: 4,
            session_memory_bytes: 1 << 20,
            factor_types: 2,
            factor_type_bytes: 4096,
            factor_type_compiles: 5,
            factor_type_reuses: 7,
            uptime_seconds: 1.5,
        }
    }

    /// The value of the sample line `series` (name and labels, exactly as rendered).
    fn sample(text: &str, series: &str) -> Option<f64> {
        text.lines()
            .find_map(|l| l.strip_prefix(series)?.strip_prefix(' ')?.parse().ok())
    }

    #[test]
    fn a_scrape_has_process_metrics_build_info_and_every_documented_metric() {
        let text = render(&gauges());
        assert_eq!(
            sample(
                &text,
                &format!(
                    "factord_build_info{{version=\"{}\"}}",
                    env!("CARGO_PKG_VERSION")
                )
            ),
            Some(1.0),
            "{text}"
        );
        #[cfg(target_os = "linux")]
        {
            let rss = sample(&text, "process_resident_memory_bytes").unwrap_or(0.0);
            assert!(rss > 1e6, "{text}");
            assert!(
                sample(&text, "process_open_fds").unwrap_or(0.0) >= 3.0,
                "{text}"
            );
            assert!(
                text.contains("# TYPE process_cpu_seconds_total counter"),
                "{text}"
            );
            assert!(sample(&text, "process_start_time_seconds").unwrap_or(0.0) > 1e9);
        }
        assert_eq!(sample(&text, "factord_sessions"), Some(3.0));
        assert_eq!(
            sample(&text, "factord_session_memory_bytes"),
            Some(1048576.0)
        );
        assert_eq!(sample(&text, "factord_uptime_seconds"), Some(1.5));
        assert_eq!(sample(&text, "factord_factor_type_bytes"), Some(4096.0));
        assert_eq!(sample(&text, TYPE_REUSES), Some(7.0));
        for (name, kind) in [
            ("factord_workers", "gauge"),
            (SOLVES, "counter"),
            (ITERATIONS, "counter"),
            (ACCEPTED_BATCHES, "counter"),
            (SLOW_FSYNCS, "counter"),
            (REJECTED, "counter"),
            (SOLVE_SECONDS, "histogram"),
            (FSYNC_SECONDS, "histogram"),
        ] {
            assert!(
                text.contains(&format!("# TYPE {name} {kind}\n")),
                "{name}: {text}"
            );
        }
        assert!(text.contains("# HELP factord_journal_fsync_seconds Journal fsync latency\n"));
    }

    #[test]
    fn histograms_keep_their_bounds_and_counters_count() {
        let before = render(&gauges());
        observe_solve(Duration::from_millis(3), 7);
        observe_fsync(Duration::from_micros(70));
        observe_fsync(Duration::ZERO); // not an fsync: not counted
        observe_fsync(SLOW_FSYNC + Duration::from_millis(1));
        count_accepted_batch();
        let after = render(&gauges());
        let delta =
            |series: &str| sample(&after, series).unwrap() - sample(&before, series).unwrap();
        // Other tests in this process record too: at least ours.
        assert!(delta(SOLVES) >= 1.0);
        assert!(delta(ITERATIONS) >= 7.0);
        assert!(delta(ACCEPTED_BATCHES) >= 1.0);
        assert!(delta("factord_solve_duration_seconds_bucket{le=\"0.005\"}") >= 1.0);
        assert!(delta("factord_journal_fsync_seconds_bucket{le=\"0.0001\"}") >= 1.0);
        assert!(delta(SLOW_FSYNCS) >= 1.0);
        assert!(delta("factord_journal_fsync_seconds_bucket{le=\"0.1\"}") >= 2.0);
        for (name, bounds) in [
            (SOLVE_SECONDS, SOLVE_BUCKETS),
            (FSYNC_SECONDS, FSYNC_BUCKETS),
        ] {
            let les: Vec<String> = after
                .lines()
                .filter_map(|l| {
                    l.strip_prefix(&format!("{name}_bucket{{le=\""))?
                        .split('"')
                        .next()
                })
                .map(str::to_owned)
                .collect();
            let mut want: Vec<String> = bounds.iter().map(f64::to_string).collect();
            want.push("+Inf".into());
            assert_eq!(les, want, "{name}");
            let count = sample(&after, &format!("{name}_count")).unwrap();
            let inf = sample(&after, &format!("{name}_bucket{{le=\"+Inf\"}}")).unwrap();
            assert_eq!(count, inf, "{name}: cumulative buckets end at _count");
        }
    }

    #[test]
    fn rejections_count_by_reason_and_only_client_errors() {
        let body = |status, code: &str| crate::api::error::ErrorBody {
            status,
            ..crate::api::error::ServiceError::bad_request(code, "f", "m").body
        };
        count_rejection(&body(400, "metrics_test_reason"));
        count_rejection(&body(400, "metrics_test_reason"));
        count_rejection(&body(503, "metrics_test_busy"));
        let text = render(&gauges());
        assert_eq!(
            sample(
                &text,
                "factord_rejected_inputs_total{reason=\"metrics_test_reason\"}"
            ),
            Some(2.0)
        );
        assert!(!text.contains("metrics_test_busy"), "{text}");
    }
}
