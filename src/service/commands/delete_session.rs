//! `delete_session`: the session and its files.

use std::sync::Arc;

use crate::api::{DeleteSession, Deleted, ServiceError};
use crate::journal::SessionDir;
use crate::service::{Caller, Service};

impl Service {
    /// Deletes session `name`. A durable session's directory is first renamed to a tombstone
    /// (fsynced: from then on it stays deleted across a crash), then removed; when the rename
    /// fails the session is not deleted (503 `delete_failed`). A failed removal of the tombstone
    /// is only logged: the deletion is durable already and the next start removes it. A session
    /// being recovered cannot be deleted yet (503 `recovering`); a corrupt one can.
    pub(super) fn delete_session(
        &self,
        caller: &Caller,
        request: DeleteSession,
    ) -> Result<Deleted, ServiceError> {
        let name = request.session.as_str();
        let session = match self.writable_as(caller, name) {
            Ok(session) => session,
            Err(e) if e.body.code == "session_corrupt" => self.session_as(caller, name)?,
            Err(e) => return Err(e),
        };
        // Under the registry's lock, as creation is: the name cannot be created again between
        // the rename and the removal from the registry.
        let mut sessions = self.sessions.write().unwrap_or_else(|p| p.into_inner());
        if !sessions.get(name).is_some_and(|s| Arc::ptr_eq(s, &session)) {
            return Err(ServiceError::not_found("session", name));
        }
        let tombstone = match &self.journal {
            Some((state_dir, _)) => session
                .bury_files(|| SessionDir::bury(state_dir, name))
                .map_err(|e| {
                    if let crate::journal::JournalError::Superseded { .. } = e {
                        session.mark_moved();
                        return crate::session::ownership_lost(name);
                    }
                    tracing::error!(session = name, "delete refused: {e}");
                    ServiceError::unavailable(
                        "delete_failed",
                        format!("session `{name}` was not deleted: its directory could not be moved aside: {e}"),
                        5,
                    )
                })?,
            None => None,
        };
        sessions.remove(name);
        drop(sessions);
        session.mark_deleted();
        if let Some(fleet) = self.fleet() {
            fleet.set_loaded(name, false);
            fleet.unlock(name);
        }
        if let Some(Err(e)) = tombstone.map(|t| t.purge()) {
            tracing::warn!(
                session = name,
                "deleted, but its files could not be removed (the next start removes them): {e}"
            );
        }
        Ok(Deleted {
            deleted: request.session,
        })
    }
}
