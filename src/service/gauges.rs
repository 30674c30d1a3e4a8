//! What the service reports on `GET /metrics`: its gauges, read at each scrape, with the
//! distinct compiled factor types counted once however many sessions share them.

use super::{Caller, Service};
use crate::runtime::metrics;

impl Service {
    /// The Prometheus text of `GET /metrics`: the process's counters, histograms and `process_*`
    /// metrics, and this service's gauges.
    pub fn metrics_text(&self) -> String {
        let health = self.health(&Caller::Trusted);
        let sessions = self.sessions();
        let types = self.type_compiler.interner.held();
        metrics::render(&metrics::Gauges {
            sessions: health.sessions,
            sessions_recovering: sessions.iter().filter(|s| s.is_recovering()).count(),
            queued: health.queued,
            busy_workers: health.busy_workers,
            workers: health.workers,
            // A type shared by sessions is charged to each of them, but held once.
            session_memory_bytes: sessions
                .iter()
                .map(|s| s.memory_bytes().saturating_sub(s.factor_type_bytes()))
                .sum::<usize>()
                + types.bytes,
            factor_types: types.types,
            factor_type_bytes: types.bytes,
            factor_type_compiles: self.type_compiler.interner.compiles(),
            factor_type_reuses: self.type_compiler.interner.reuses(),
            uptime_seconds: health.uptime_seconds,
        })
    }
}
