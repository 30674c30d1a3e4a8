//! Sessions moving between the instances of a fleet. On every membership change, and on a
//! safety tick, each instance compares what it holds with what placement gives it:
//!
//! - **Adoption**: a session directory on disk that this instance owns and has not loaded is
//!   locked (without waiting; a lock still held by an instance releasing it, or by one not yet
//!   dead, is tried again on the next, faster tick), its next ownership epoch claimed and its
//!   files carried over (`journal::takeover`), and it is recovered from them as at start
//!   ([`Service::recover_one`]).
//! - **Takeover from a stopped instance**: a lock held by an instance that is gone from the
//!   membership and whose heartbeat stopped a lease ago (`fleet_heartbeat`), or by one that
//!   released the session cleanly, does not stop an adoption: the new epoch fences the holder
//!   (it acknowledges nothing more, `ownership_lost`), and the lock is taken once it is free.
//! - **Stepping down**: a loaded session whose epoch another instance claimed (this instance
//!   was stopped meanwhile) is dropped here without touching its files: writes hear
//!   `session_moving` and go to the new owner.
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
        self.release_foreign(fleet);
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
            let broken = || {
                fleet
                    .broken
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .contains(&name)
            };
            if fleet.owner_of(&name) != fleet.instance()
                || self.session(&name).is_ok()
                || fleet.is_moving(&name)
                || broken()
            {
                continue;
            }
            again |= !self.adopt(fleet, name, dir, &config);
        }
        again
    }

    /// Steps down from the sessions this instance no longer owns (another took them over) and
    /// releases those placed elsewhere; locks the ones taken over without their lock once free.
    fn release_foreign(self: &Arc<Self>, fleet: &Arc<Fleet>) {
        for session in self.sessions() {
            if fleet.is_moving(&session.name) {
                continue;
            }
            if session.ownership_superseded() {
                self.step_down(fleet, &session.name);
            } else if fleet.owner_of(&session.name) != fleet.instance() {
                self.release(fleet, &session.name);
            } else {
                // Taken over without its lock (its holder stopped): lock it once it is free.
                fleet.lock_loaded(&session.name);
            }
        }
    }

    /// Adopts session `name`, which this instance owns and does not hold: its lock (or a take-
    /// over from a stopped holder), a new ownership epoch, then its recovery. `false`: not yet
    /// possible (try again soon). A session that does not recover is marked broken.
    fn adopt(
        self: &Arc<Self>,
        fleet: &Arc<Fleet>,
        name: String,
        dir: SessionDir,
        config: &crate::journal::JournalConfig,
    ) -> bool {
        let lock = match SessionLock::try_acquire(dir.path()) {
            Ok(lock) => Some(lock),
            Err(LockError::Held) => match dir.latest_claim() {
                Ok(Some((n, holder, _)))
                    if fleet.may_take_over(Some((n, holder.clone())), dir.path()) =>
                {
                    tracing::warn!(
                        session = %name,
                        "fleet: taking over from `{holder}` (stopped, or released it)"
                    );
                    None
                }
                _ => return false,
            },
            Err(LockError::Gone) => return true,
            Err(LockError::Io(e)) => {
                tracing::warn!(session = %name, "fleet: cannot lock its directory: {e}");
                return false;
            }
        };
        // Deleted between the listing and the lock: nothing to adopt.
        if !dir.path().join("session.json").exists() {
            return true;
        }
        let dir = match dir.take_over(fleet.instance()) {
            Ok(dir) => dir,
            Err(e) => {
                tracing::warn!(session = %name, "fleet: cannot take it over yet: {e}");
                return false;
            }
        };
        if let Some(lock) = lock {
            fleet
                .locks
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .insert(name.clone(), lock);
        }
        tracing::info!(session = %name, epoch = dir.epoch(), "fleet: adopting");
        if !self.recover_one(name.clone(), dir, config) {
            fleet.unlock(&name);
            fleet
                .broken
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .insert(name);
        }
        true
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
        let dir = session.journal_dir();
        // Waits for a snapshot being written, then closes the journal: nothing writes there
        // from here on, and the successor need not wait for this instance's lock.
        match session.bury_files(|| Ok(())) {
            Ok(()) => {
                if let Some(Err(e)) = dir.map(|d| d.release()) {
                    tracing::warn!(session = name, "fleet: marking it released: {e}");
                }
            }
            Err(e) => tracing::warn!(session = name, "fleet: closing its journal: {e}"),
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

    /// Drops session `name`, which another instance took over while this one was stopped:
    /// its files are the new owner's, so nothing is synced or written (see the module doc).
    fn step_down(self: &Arc<Self>, fleet: &Arc<Fleet>, name: &str) {
        let Ok(session) = self.session(name) else {
            return;
        };
        tracing::warn!(
            session = name,
            "fleet: taken over by another instance: stepping down"
        );
        session.mark_moved();
        {
            let mut sessions = self.sessions.write().unwrap_or_else(|p| p.into_inner());
            if sessions.get(name).is_some_and(|s| Arc::ptr_eq(s, &session)) {
                sessions.remove(name);
            }
        }
        fleet.set_loaded(name, false);
        fleet.unlock(name);
    }
}
