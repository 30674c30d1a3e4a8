//! Start-up: every session found in the state directory is listed at once and rebuilt from its
//! snapshot and journal in the background; unnamed creations continue after the names found.
//! In a fleet only the sessions this instance owns are loaded, by adoption (`fleet_moves.rs`),
//! one at a time through the same [`Service::recover_one`].

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use super::Service;
use crate::journal::{JournalConfig, SessionDir};

/// How often sessions' histories are written to their directories (when they changed).
const HISTORY_PERSISTENCE_PERIOD: Duration = Duration::from_secs(1);

impl Service {
    /// Rebuilds every session found in the state directory, each in the background: it is
    /// listed at once (with `recovering` in its statistics, writes refused with 503) and
    /// optimised when its journal has been replayed. Returns how many there are. In a fleet,
    /// loads nothing (adoption does, once the membership is known).
    pub fn recover_sessions(self: &Arc<Self>) -> Result<usize, crate::journal::JournalError> {
        let Some((state_dir, config)) = self.journal.clone() else {
            return Ok(0);
        };
        self.finish_deletions();
        self.start_journal_sync(&config);
        self.start_history_persistence();
        if self.fleet().is_some() {
            return Ok(0);
        }
        let found = SessionDir::list(&state_dir)?;
        let names_on_disk = SessionDir::names_on_disk(&state_dir)?;
        // Unnamed creations continue after every name on disk, loadable or not.
        for name in &names_on_disk {
            self.reserve_generated_name(name);
        }
        let on_disk = names_on_disk.len();
        let mut count = 0;
        for (name, dir) in found {
            // A fleet's directory (ownership epochs): this single instance takes the latest
            // epoch's files over, as an instance of the fleet would (`journal::takeover`).
            let dir = match dir.latest_claim() {
                Ok(None) => dir,
                Ok(Some(_)) => match dir.take_over("standalone") {
                    Ok(dir) => dir,
                    Err(e) => {
                        tracing::error!(session = %name, "not recovered: {e}");
                        continue;
                    }
                },
                Err(e) => {
                    tracing::error!(session = %name, "not recovered: {e}");
                    continue;
                }
            };
            if self.recover_one(name, dir, &config) {
                count += 1;
            }
        }
        self.count_unloaded(on_disk.saturating_sub(count));
        Ok(count)
    }

    /// Lists session `name` from its directory at once (recovering: writes refused with 503)
    /// and rebuilds it from its snapshot and journal in the background. Only the small identity
    /// files are read here; a session whose identity cannot be read is left on disk, unlisted
    /// (its name cannot be created again): returns false.
    pub(super) fn recover_one(
        self: &Arc<Self>,
        name: String,
        dir: SessionDir,
        config: &JournalConfig,
    ) -> bool {
        let mut identity = match dir.load_identity() {
            Ok(identity) => identity,
            Err(e) => {
                tracing::error!(
                    session = %name,
                    "not recovered, its directory is kept for an operator: {e}"
                );
                return false;
            }
        };
        let auto_optimize = identity.request.auto_optimize;
        // Compiled in the background with the rest: many large types take seconds, and the
        // HTTP listener only opens once every session is listed.
        let factor_types = std::mem::take(&mut identity.request.factor_types);
        let compiler = self.type_compiler.clone();
        let no_types_yet = FactorTypes::new(compiler.clone());
        let session = match self.build_session(name.clone(), identity.request, Some(no_types_yet)) {
            Ok(session) => session,
            Err(e) => {
                tracing::error!(session = %name, "not recovered: {}", e.body.message);
                return false;
            }
        };
        session.mark_recovering();
        if let Some(owner) = &identity.owner {
            session.set_owner(owner.as_str().into());
        }
        self.register(name.clone(), Arc::clone(&session));
        let config = config.clone();
        let rebuild = move || {
            let _span = tracing::info_span!("session", session = %name).entered();
            // The types first (sessions recovering with the same ones compile them once, see
            // `TypeInterner`), then the snapshot and journal, off start-up: they can be large.
            let outcome = FactorTypes::recovered(compiler, session.kind, &factor_types)
                .map(|types| session.set_factor_types(types))
                .map_err(|e| format!("factor types: {}", e.body.message))
                .and_then(|()| dir.load_state().map_err(|e| e.to_string()))
                .and_then(|recovered| {
                    let journal = dir.open_journal(config.fsync).map_err(|e| e.to_string())?;
                    Ok((recovered, journal))
                })
                .and_then(|(recovered, journal)| {
                    let durability = crate::session::Durability {
                        dir,
                        journal,
                        config,
                    };
                    session.recover(auto_optimize, recovered, durability)
                });
            match outcome {
                Ok(r) if r.corruption.is_some() => tracing::error!(
                    entries = r.entries,
                    "journal damaged, session recovered up to the damage and read-only: {}",
                    r.corruption.unwrap_or_default()
                ),
                Ok(r) => tracing::info!(
                    entries = r.entries,
                    truncated_bytes = r.truncated_bytes,
                    seconds = r.seconds,
                    "recovered from snapshot {:?} and journal",
                    r.snapshot_sequence
                ),
                Err(e) => {
                    tracing::error!("recovery failed, session kept as far as it got: {e}");
                    session.recovery_failed(&e);
                }
            }
        };
        // At most one session per worker is rebuilt at a time: ten sessions compiling their
        // types at once on two cores left start-up itself (the HTTP listener included) a
        // sixth of the CPU, and spread their memory over ten allocator arenas.
        let slots = Arc::clone(&self.recovery_slots);
        tokio::spawn(async move {
            let _slot = slots.acquire_owned().await;
            let _ = tokio::task::spawn_blocking(rebuild).await;
        });
        true
    }

    /// Under `fsync: interval`: fsyncs every session's journal every `interval_ms`.
    fn start_journal_sync(self: &Arc<Self>, config: &JournalConfig) {
        if config.fsync != crate::journal::Fsync::Interval {
            return;
        }
        let period = Duration::from_millis(config.interval_ms.max(1));
        self.every_session_every(period, Session::sync_journal);
    }

    /// Writes every durable session's history to its directory once a second, where it
    /// changed (see `Session::persist_history`): a restart loses at most the last second of
    /// the operators' timeline and log.
    fn start_history_persistence(self: &Arc<Self>) {
        self.every_session_every(HISTORY_PERSISTENCE_PERIOD, Session::persist_history);
    }

    /// Runs `each` on every session, on a blocking thread (file I/O), every `period` for as
    /// long as the service lives.
    fn every_session_every(self: &Arc<Self>, period: Duration, each: fn(&Session)) {
        let service = Arc::downgrade(self);
        self.runtime.spawn(async move {
            loop {
                tokio::time::sleep(period).await;
                let Some(service) = service.upgrade() else {
                    return;
                };
                let sessions = service.sessions();
                drop(service);
                let _ = tokio::task::spawn_blocking(move || {
                    for s in sessions {
                        each(&s);
                    }
                })
                .await;
            }
        });
    }

    /// Unnamed creations (`s<n>`) are numbered after `name` when it is one of theirs.
    fn reserve_generated_name(&self, name: &str) {
        if let Some(n) = name.strip_prefix('s').and_then(|n| n.parse::<u64>().ok()) {
            self.next_id
                .fetch_max(n.saturating_add(1), Ordering::SeqCst);
        }
    }

    /// Lists a recovered session.
    fn register(&self, name: String, session: Arc<Session>) {
        self.notify_observers(&session);
        self.sessions
            .write()
            .unwrap_or_else(|p| p.into_inner())
            .insert(name, session);
    }
}

use crate::session::factor_types::FactorTypes;
use crate::session::Session;
