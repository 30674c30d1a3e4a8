//! Sessions moving between the instances of a fleet. On every membership change, and on a
//! safety tick, each instance compares what it holds with what placement gives it:
//!
//! - **Adoption**: a session directory on disk that this instance owns and has not loaded is
//!   locked (without waiting; a lock still held by an instance releasing it, or by one not yet
//!   dead, is tried again on the next, faster tick) and recovered from its snapshot and journal
//!   as at start ([`Service::recover_one`]).
//! - **Release**: a loaded session another instance now owns (it joined) stops taking writes
//!   (503 `session_moving`), its running solve is stopped, its journal synced and closed (a
//!   snapshot being written finishes first), it leaves the registry and its lock is dropped; the
//!   new owner adopts it on its next tick.

use std::sync::Arc;
use std::time::Duration;

use super::fleet::Fleet;
use super::fleet_lock::{LockError, SessionLock};
use super::Service;
use crate::journal::SessionDir;

/// The safety tick: membership changes wake the loop at once, this catches anything else.
const TICK: Duration = Duration::from_secs(1);
/// The tick while a session this instance owns is still locked by another (releasing) one.
const RETRY: Duration = Duration::from_millis(100);

impl Service {
    /// Runs the rebalancing loop until the service stops.
    pub(super) fn start_rebalancing(self: &Arc<Self>, fleet: Arc<Fleet>) {
        let service = Arc::downgrade(self);
        self.runtime.spawn(async move {
            let mut wait = TICK;
            loop {
                tokio::select! {
                    () = fleet.changed.notified() => {}
                    () = tokio::time::sleep(wait) => {}
                }
                let Some(service) = service.upgrade() else {
                    return;
                };
                if service.pool.handle().is_stopping() {
                    return;
                }
                if !fleet.settled() {
                    continue;
                }
                let again = {
                    let (service, fleet) = (Arc::clone(&service), Arc::clone(&fleet));
                    // Listing the directory and opening files: off the async threads.
                    tokio::task::spawn_blocking(move || service.rebalance(&fleet))
                        .await
                        .unwrap_or(true)
                };
                wait = if again { RETRY } else { TICK };
            }
        });
    }

    /// One pass: releases what others own, adopts what this instance owns. Returns whether a
    /// session this instance owns could not be locked yet (try again soon).
    fn rebalance(self: &Arc<Self>, fleet: &Arc<Fleet>) -> bool {
        for session in self.sessions() {
            if fleet.owner_of(&session.name) != fleet.instance() && !fleet.is_moving(&session.name)
            {
                self.release(fleet, &session.name);
            }
        }
        let Some((state_dir, config)) = self.journal.clone() else {
            return false;
        };
        let found = match SessionDir::list(&state_dir) {
            Ok(found) => found,
            Err(e) => {
                tracing::warn!("fleet: cannot list the session directories: {e}");
                return true;
            }
        };
        let mut again = false;
        for (name, dir) in found {
            if fleet.owner_of(&name) != fleet.instance()
                || self.session(&name).is_ok()
                || fleet.is_moving(&name)
                || fleet
                    .broken
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .contains(&name)
            {
                continue;
            }
            let lock = match SessionLock::try_acquire(dir.path()) {
                Ok(lock) => lock,
                Err(LockError::Held) => {
                    again = true;
                    continue;
                }
                Err(LockError::Gone) => continue,
                Err(LockError::Io(e)) => {
                    tracing::warn!(session = %name, "fleet: cannot lock its directory: {e}");
                    again = true;
                    continue;
                }
            };
            // Deleted between the listing and the lock: nothing to adopt.
            if !dir.path().join("session.json").exists() {
                continue;
            }
            fleet
                .locks
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .insert(name.clone(), lock);
            tracing::info!(session = %name, "fleet: adopting");
            if !self.recover_one(name.clone(), dir, &config) {
                fleet.unlock(&name);
                fleet
                    .broken
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .insert(name);
            }
        }
        again
    }

    /// Hands session `name` over to its new owner (see the module's documentation). Blocking.
    fn release(self: &Arc<Self>, fleet: &Arc<Fleet>, name: &str) {
        let Ok(session) = self.session(name) else {
            return;
        };
        fleet
            .moving
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .insert(name.to_string());
        tracing::info!(session = name, "fleet: releasing to its new owner");
        // Writes racing this see it moving (checked under its lock: 503 session_moving, so
        // their clients retry and reach the new owner); waiters wake.
        session.mark_moved();
        session.sync_journal();
        session.persist_history();
        // Waits for a snapshot being written, then closes the journal: nothing writes there
        // from here on.
        if let Err(e) = session.bury_files(|| Ok(())) {
            tracing::warn!(session = name, "fleet: closing its journal: {e}");
        }
        {
            let mut sessions = self.sessions.write().unwrap_or_else(|p| p.into_inner());
            if sessions.get(name).is_some_and(|s| Arc::ptr_eq(s, &session)) {
                sessions.remove(name);
            }
        }
        fleet.set_loaded(name, false);
        fleet.unlock(name);
        fleet
            .moving
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .remove(name);
        tracing::info!(session = name, "fleet: released");
    }
}
