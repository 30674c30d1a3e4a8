//! The session's history in its directory (`history.json`, see `session::history`): written
//! when it changed, from a copy taken under the history's lock and serialised after it, by the
//! service's once-a-second pass, at shutdown and before a fleet hands the session over; read
//! back when the session is rebuilt. The history is the operators' view of the stream, not
//! the session's state: a file that cannot be written or read is logged, never an error.

use std::sync::Arc;

use super::super::history::{History, StoredEvent, StoredHistory, STORED_HISTORY_FORMAT};
use super::super::Session;
use crate::journal::SessionDir;

impl Session {
    /// Writes the history to the session's directory if it changed since the last write.
    /// Durable sessions only, and not while recovering (the history is being rebuilt) or
    /// damaged (its files are kept as they are). Blocking: file I/O.
    pub fn persist_history(&self) {
        if self.is_recovering() || self.corruption().is_some() {
            return;
        }
        let Some((dir, files)) = self
            .durable
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .as_ref()
            .map(|d| (d.dir.clone(), Arc::clone(&d.files)))
        else {
            return;
        };
        let Some((revision, stored)) = self
            .history
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .changed_since_written()
        else {
            return;
        };
        let bytes = match serde_json::to_vec(&stored) {
            Ok(bytes) => bytes,
            Err(e) => {
                tracing::warn!(session = self.name, "history not written: {e}");
                return;
            }
        };
        // A deletion or a hand-over (`bury_files`) waits for this write; none starts after it.
        let alive = files.lock().unwrap_or_else(|p| p.into_inner());
        if !*alive {
            return;
        }
        match dir.write_history(&bytes) {
            Ok(()) => self
                .history
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .written_at(revision),
            Err(e) => tracing::warn!(session = self.name, "history not written: {e}"),
        }
    }

    /// Takes the history `dir` kept, replacing what this process recorded so far (a replayed
    /// window's keyframes, which the stored timeline already holds). A file that cannot be
    /// read is logged and replaced at the next write.
    pub(in crate::session) fn restore_history(&self, dir: &SessionDir) {
        let bytes = match dir.load_history() {
            Ok(Some(bytes)) => bytes,
            Ok(None) => return,
            Err(e) => {
                tracing::warn!(session = self.name, "history not restored: {e}");
                return;
            }
        };
        match serde_json::from_slice::<StoredHistory<StoredEvent>>(&bytes) {
            Ok(stored) if stored.format == STORED_HISTORY_FORMAT => {
                *self.history.lock().unwrap_or_else(|p| p.into_inner()) = History::restored(stored);
            }
            Ok(stored) => tracing::warn!(
                session = self.name,
                "history file has format {}, this build reads {STORED_HISTORY_FORMAT}: the \
                 history starts afresh",
                stored.format
            ),
            Err(e) => tracing::warn!(
                session = self.name,
                "history file unreadable, the history starts afresh: {e}"
            ),
        }
    }
}
