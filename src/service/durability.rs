//! The service's side of durable sessions: creating a session's directory without ever
//! overwriting one, deleting it durably, and refusing writes to a session whose files could not
//! be recovered whole. The files themselves are `crate::journal`'s.

use std::sync::atomic::Ordering;
use std::sync::Arc;

use super::{Service, ServiceError};
use crate::api::wire::CreateSession;
use crate::journal::{JournalError, SessionDir};
use crate::session::{Durability, Session};

/// 409 `session_corrupt` for a session whose recovery found damaged files: it stays read-only
/// until an operator deletes it (retrying cannot help, so no Retry-After).
pub(super) fn refuse_if_corrupt(session: &Session) -> Result<(), ServiceError> {
    match session.corruption() {
        Some(reason) => Err(ServiceError::conflict(
            "session_corrupt",
            format!("session `{}` is read-only: {reason}", session.name),
        )),
        None => Ok(()),
    }
}

fn journal_failed(name: &str, e: &JournalError) -> ServiceError {
    ServiceError::unavailable(
        "journal_failed",
        format!("cannot create the journal of session `{name}`: {e}"),
        5,
    )
}

/// 409 `session_on_disk`: the name has a directory that was not loaded (unreadable at start,
/// or an unfinished creation). It is never overwritten; an operator repairs or removes it.
fn on_disk(name: &str, dir: &std::path::Path) -> ServiceError {
    tracing::warn!(
        session = name,
        "creation refused: {} exists on disk but is not loaded (see the start-up log); \
         it is kept for an operator to repair or remove",
        dir.display()
    );
    ServiceError::conflict(
        "session_on_disk",
        format!(
            "session `{name}` cannot be created: its directory exists on disk but could not be \
             loaded; it is kept unchanged for an operator to repair or remove"
        ),
    )
}

impl Service {
    /// At start: `n` session directories could not be loaded. They count against
    /// `max_sessions` (as the sessions they hold would after a repair) until the next start.
    pub(super) fn count_unloaded(&self, n: usize) {
        self.unloaded_on_disk.store(n, Ordering::SeqCst);
        if n > 0 {
            tracing::error!(
                "{n} session director{} could not be loaded: kept for an operator, their names \
                 cannot be created, and they count against max_sessions",
                if n == 1 { "y" } else { "ies" }
            );
        }
    }

    /// Whether session `name` has a directory in the state directory (journal enabled).
    pub(super) fn directory_on_disk(&self, name: &str) -> bool {
        self.journal.as_ref().is_some_and(|(state_dir, _)| {
            std::fs::symlink_metadata(SessionDir::sessions_root(state_dir).join(name)).is_ok()
        })
    }

    /// Before creating `name` (a name not loaded): refuses it when its directory is on disk
    /// (found unloadable at start, or an unfinished creation), and returns how many directories
    /// on disk were not loaded at start, which count against `max_sessions`. A `stat`, no file
    /// descriptor: the atomic check is [`SessionDir::create`]'s.
    pub(super) fn unloaded_on_disk(&self, name: &str) -> Result<usize, ServiceError> {
        let Some((state_dir, _)) = &self.journal else {
            return Ok(0);
        };
        let dir = SessionDir::sessions_root(state_dir).join(name);
        let exists = std::fs::symlink_metadata(&dir).is_ok();
        if self.fleet().is_some() {
            // In a fleet the directories of other instances' sessions are not loaded here; one
            // on disk is a session that exists (or a creation that did not finish).
            return match exists {
                true => Err(ServiceError::conflict(
                    "session_exists",
                    format!("session `{name}` already exists"),
                )),
                false => Ok(0),
            };
        }
        if exists {
            return Err(on_disk(name, &dir));
        }
        Ok(self.unloaded_on_disk.load(Ordering::SeqCst))
    }

    /// Creates the directory and journal of new session `name` (journal enabled). Nothing is
    /// left on disk when this fails, and an existing directory is never touched. In a fleet the
    /// new directory's lock is taken at once (see `fleet_lock`).
    pub(super) fn create_files(
        &self,
        name: &str,
        record: &CreateSession,
        owner: Option<&str>,
    ) -> Result<Option<Durability>, ServiceError> {
        let Some((state_dir, config)) = &self.journal else {
            return Ok(None);
        };
        let created = SessionDir::create(state_dir, name, record, owner);
        if let (Ok(_), Some(fleet)) = (&created, self.fleet()) {
            fleet.lock_created(name)?;
        }
        let created = created.and_then(|mut dir| {
            // In a fleet its files are those of ownership epoch 1, this instance's (see
            // `journal::takeover`).
            if let Some(fleet) = self.fleet() {
                if let Err(e) = dir.claim_first(fleet.instance()) {
                    return Err(dir.roll_back(e));
                }
            }
            let journal = dir.open_journal(config.fsync);
            match journal {
                Ok(journal) => Ok(Durability {
                    dir,
                    journal,
                    config: config.clone(),
                }),
                Err(e) => Err(dir.roll_back(e)),
            }
        });
        match created {
            Ok(durability) => Ok(Some(durability)),
            Err(JournalError::Exists { path }) => Err(on_disk(name, &path)),
            Err(e) => {
                tracing::error!(session = name, "creation refused: {e}");
                if let Some(fleet) = self.fleet() {
                    fleet.unlock(name);
                }
                Err(journal_failed(name, &e))
            }
        }
    }

    /// At start: removes the directories of sessions deleted before a crash or a failed removal.
    pub(super) fn finish_deletions(&self) {
        if let Some((state_dir, _)) = &self.journal {
            for e in SessionDir::finish_deletions(state_dir) {
                tracing::warn!("a deleted session's files could not be removed: {e}");
            }
        }
    }
}

/// Applies a batch that waits for its fsync without holding an async thread: a disk stall
/// would otherwise stop every other request of this instance, and the fsyncs of many batches
/// run at once, so they are grouped (`journal::group_commit`). `block_in_place` keeps the batch
/// on its thread (no hand-off to wait for) and hands the thread's other tasks to another one;
/// a current-thread runtime (tests, embedding) has no other thread: a blocking one is used.
pub(super) async fn apply_waiting_for_fsync(
    session: &Arc<crate::session::Session>,
    batch: crate::api::wire::Batch,
) -> Result<(crate::api::wire::BatchAck, bool), ServiceError> {
    use tokio::runtime::{Handle, RuntimeFlavor};
    if Handle::current().runtime_flavor() == RuntimeFlavor::MultiThread {
        return tokio::task::block_in_place(|| session.apply_batch(batch));
    }
    let session = Arc::clone(session);
    super::off_async("batch", move || session.apply_batch(batch)).await
}
