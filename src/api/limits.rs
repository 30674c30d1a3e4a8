//! The service's capacity limits (`limits` in the server configuration).

use serde::{Deserialize, Serialize};

/// Capacity limits.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Limits {
    /// Solver threads (default: the number of cores).
    pub workers: usize,
    pub max_sessions: usize,
    /// Factors a session may have waiting for its running solve before batches get 429.
    pub max_pending_factors: usize,
    /// Batch jobs running or queued at once before new ones get 503.
    pub max_jobs: usize,
    /// How long `wait` requests wait for a solve.
    pub wait_timeout_ms: u64,
    /// Largest batch: variables + factors + removals + fixes + guesses (413 beyond).
    pub max_batch_items: usize,
    /// Variables and live factors one session may hold (422 `session_full` beyond).
    pub max_variables_per_session: usize,
    pub max_factors_per_session: usize,
    /// Estimated bytes one session may hold (`memory_bytes` in its statistics): a batch that
    /// adds variables or factors to a session already past it gets 422 `session_full` (a batch
    /// that only removes, fixes or re-guesses still passes). One session streaming without end
    /// must not take the memory every other session lives in. Default: a quarter of the
    /// machine's physical memory (4 GiB where it cannot be read).
    pub max_session_memory_bytes: u64,
    /// A session's solve or a batch job stops after this long (its preempted turns added up),
    /// keeping the best estimate it reached; `last_error` (sessions) or the Summary's
    /// `interrupted` termination (jobs) says so.
    pub max_solve_ms: u64,
    /// Admitting one batch (building its factors, checking their residuals, under the
    /// session's lock) is refused with 413 `batch_too_costly` past this long. Its own limit, not
    /// `max_solve_ms`: a short solve bound must not refuse ordinary large batches.
    pub max_admission_ms: u64,
    /// A batch job whose solve is estimated (from the graph and its symbolic factorisation) to
    /// need more memory than this is refused with 413 `job_too_large` before it starts.
    pub max_job_memory_bytes: u64,
    /// What one session's user-defined factor types may hold (estimated bytes of their
    /// compiled tapes and definitions, each type counted in full even when shared with other
    /// sessions): declarations past it are refused with 413 `factor_types_too_large`.
    pub max_factor_type_bytes_per_session: usize,
    /// What the server's compiled factor types may hold, each distinct type counted once:
    /// declaring a type no session holds yet is refused past it with 413
    /// `factor_types_server_full` (a type already held is shared at no cost).
    pub max_factor_type_bytes: usize,
    /// Event-stream subscribers per session (SSE and WebSocket clients; the zenoh publisher
    /// counts as one) before new ones get 429.
    pub max_subscribers: usize,
    /// Events a subscriber may fall behind a session (the events published since the oldest
    /// one it has not taken) before it gets a `lagged` marker and the latest values instead of
    /// the events it missed. The session holds that many events for its slowest subscriber.
    pub max_subscriber_lag: usize,
    /// The most bytes of published events a session keeps for subscribers that have not taken
    /// them yet (the newest is kept whatever its size): a subscriber further behind gets the
    /// `lagged` marker as above. Events of a large map's corrections are megabytes each.
    pub max_subscriber_lag_bytes: usize,
    /// Distinct producer ids (exactly-once ingest) one session keeps before a batch naming a
    /// new one gets 422 `too_many_producers`: each is kept, with its acknowledgements, for good.
    pub max_producers_per_session: usize,
}

impl Default for Limits {
    fn default() -> Self {
        let cores = std::thread::available_parallelism().map_or(2, |n| n.get());
        Self {
            workers: cores,
            max_sessions: 1024,
            max_pending_factors: 200_000,
            max_jobs: 2 * cores,
            wait_timeout_ms: 120_000,
            max_batch_items: 1_000_000,
            max_variables_per_session: 10_000_000,
            max_factors_per_session: 50_000_000,
            max_session_memory_bytes: physical_memory_bytes().map_or(4 << 30, |total| total / 4),
            max_solve_ms: 600_000,
            // Ten seconds of one session's lock: the costliest user-defined factors admit
            // ~20 000 in that time; ordinary ones millions.
            max_admission_ms: 10_000,
            // A sixth of a 24 GB machine: a few such jobs fit at once, with the sessions.
            max_job_memory_bytes: 4 << 30,
            // The largest type compiles to ~4 MB: 32 of them fit one session. Sixteen
            // sessions of such types, all different, fill the server's bound (a twelfth of
            // 24 GB).
            max_factor_type_bytes_per_session: 256 << 20,
            max_factor_type_bytes: 2 << 30,
            max_subscribers: 64,
            max_subscriber_lag: 4096,
            max_subscriber_lag_bytes: 64 << 20,
            max_producers_per_session: 1024,
        }
    }
}

/// The machine's physical memory (`MemTotal` of `/proc/meminfo`), where it can be read.
fn physical_memory_bytes() -> Option<u64> {
    let meminfo = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = meminfo.lines().find(|l| l.starts_with("MemTotal:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}
