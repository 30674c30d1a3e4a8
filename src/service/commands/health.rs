//! `health`: the service's load; open to every caller (and answered while shutting down).

use crate::api::catalogue;
use crate::api::Health;
use crate::service::{Caller, Service};

impl Service {
    /// The service's health; `sessions` counts the sessions `caller` may see.
    pub fn health(&self, caller: &Caller) -> Health {
        let pool = self.pool.handle();
        Health {
            status: if pool.is_stopping() { "stopping" } else { "ok" },
            version: env!("CARGO_PKG_VERSION"),
            workers: self.pool.workers,
            busy_workers: pool.busy(),
            queued: pool.waiting(),
            sessions: {
                let sessions = self.sessions.read().unwrap_or_else(|p| p.into_inner());
                sessions.values().filter(|s| caller.may_see(s)).count()
            },
            session_kinds: catalogue::SESSION_KINDS.iter().map(|k| k.name).collect(),
            uptime_seconds: self.started.elapsed().as_secs_f64(),
        }
    }
}
