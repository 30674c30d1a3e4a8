//! Acknowledging a write that waits for its fsync: group commit (`journal::group_commit`)
//! without the journal held, then the fleet's ownership fence (`journal::takeover`): what a
//! batch waits for, what a refused one does to the session, and the checks a fleet's
//! rebalancing asks of a loaded session.

use super::super::Session;
use super::{journal_failed, Durable};
use crate::api::ServiceError;
use crate::journal::SessionDir;

/// A batch written to the journal, to be made durable without holding the journal: batches of
/// one session (and the fdatasyncs of many) are then grouped (`journal::group_commit`).
pub(in crate::session) struct PendingSync {
    ticket: Option<crate::journal::group_commit::Ticket>,
    dir: SessionDir,
}

impl PendingSync {
    /// Waits until the batch's record is durable (under `fsync always`), then checks that this
    /// instance still owns the session (the fence, see `journal::takeover`).
    pub(in crate::session) fn wait(self, name: &str) -> Result<(), ServiceError> {
        if let Some(ticket) = self.ticket {
            let waited = ticket.wait().map_err(|e| journal_failed(name, e))?;
            crate::runtime::metrics::observe_fsync(waited);
        }
        if self.dir.superseded() {
            return Err(crate::session::ownership_lost(name));
        }
        Ok(())
    }
}

impl Durable {
    /// What a batch just written waits for, after releasing the journal (see
    /// [`PendingSync::wait`]).
    pub(in crate::session) fn pending(&self) -> PendingSync {
        PendingSync {
            ticket: self.journal.last_ticket(),
            dir: self.dir.clone(),
        }
    }
}

impl Session {
    /// Waits until every batch whose entry is in the journal is durable (a failure is the
    /// batch's own to report). What a solve publishes, and a repeated acknowledgement, pass it
    /// first.
    pub(in crate::session) fn journal_barrier(&self) {
        let ticket = self
            .durable
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .as_ref()
            .and_then(|d| d.journal.last_ticket());
        if let Some(ticket) = ticket {
            let _ = ticket.wait();
        }
        // And every batch written so far has been acknowledged (see `Session::acknowledging`).
        drop(
            self.acknowledging
                .write()
                .unwrap_or_else(|p| p.into_inner()),
        );
    }

    /// A write's sync was refused: the session was taken over elsewhere (it steps down here:
    /// every later request hears `session_moving` and goes to the new owner), or its journal
    /// failed ([`Self::journal_sync_failed`]). Call without the journal held.
    pub(in crate::session) fn sync_refused(&self, error: ServiceError) -> ServiceError {
        if error.body.code != "ownership_lost" {
            return self.journal_sync_failed(error);
        }
        tracing::warn!(
            session = self.name,
            "taken over by another instance: stepping down"
        );
        self.mark_moved();
        error
    }

    /// Whether an accepted write waits for an fsync (a durable session under `fsync always`).
    pub fn waits_for_fsync(&self) -> bool {
        self.durable
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .as_ref()
            .is_some_and(|d| d.config.fsync == crate::journal::Fsync::Always)
    }

    /// Whether another instance of the fleet took the session over (see `journal::takeover`).
    /// Waits for a write's fsync under way.
    pub fn ownership_superseded(&self) -> bool {
        self.durable
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .as_ref()
            .is_some_and(|d| d.dir.superseded())
    }

    /// Its directory, at the ownership epoch it writes (`None` outside the journal).
    pub fn journal_dir(&self) -> Option<SessionDir> {
        self.durable
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .as_ref()
            .map(|d| d.dir.clone())
    }
}
