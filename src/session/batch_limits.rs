//! The limits a client's batch is held to before it is journaled: its items, the session's
//! memory, and the session's variables and factors (`limits.*` in the configuration).

use super::batch::PreparedBatch;
use super::{Session, State};
use crate::api::wire::Batch;
use crate::api::ErrorKind;
use crate::api::ServiceError;

impl Session {
    /// A batch of more items than `limits.max_batch_items` is refused whole.
    pub(super) fn check_batch_size(&self, batch: &Batch) -> Result<(), ServiceError> {
        let items = batch.variables.len()
            + batch.factors.len()
            + batch.remove_factors.len()
            + batch.fix.len()
            + batch.unfix.len()
            + batch.guesses.len();
        if items > self.limits.max_batch_items {
            return Err(ServiceError::new(
                ErrorKind::TooLarge,
                "batch_too_large",
                format!(
                    "the batch has {items} items (variables, factors, removals, fixes, guesses); the limit is {} (limits.max_batch_items): split it",
                    self.limits.max_batch_items
                ),
            )
            .at("batch"));
        }
        Ok(())
    }

    /// A batch that adds variables or factors to a session past
    /// `limits.max_session_memory_bytes` is refused (read before the journal's lock: the
    /// estimate counts the journal's own memory).
    pub(super) fn check_session_memory(
        &self,
        st: &State,
        batch: &Batch,
    ) -> Result<(), ServiceError> {
        let adds = !(batch.variables.is_empty() && batch.factors.is_empty());
        let held = self.memory_bytes_locked(st) as u64;
        if adds && held > self.limits.max_session_memory_bytes {
            const MIB: u64 = 1 << 20;
            return Err(ServiceError::invalid(
                "session_full",
                "batch",
                format!(
                    "session `{}` holds about {} MiB, more than limits.max_session_memory_bytes ({} MiB): it takes no more variables or factors (removals still pass); start a new session or raise the limit",
                    self.name,
                    held / MIB,
                    self.limits.max_session_memory_bytes / MIB
                ),
            ));
        }
        Ok(())
    }

    /// A batch after which the session would hold more variables or factors than its limits
    /// is refused.
    pub(super) fn check_session_size(
        &self,
        st: &State,
        prepared: &PreparedBatch,
    ) -> Result<(), ServiceError> {
        // The setting is named after the field: limits.max_variables_per_session, ….
        let full = |field: &'static str, count: usize, limit: usize| {
            ServiceError::invalid(
                "session_full",
                field,
                format!(
                    "session `{}` would hold {count} {field}; the limit is {limit} (limits.max_{field}_per_session)",
                    self.name
                ),
            )
        };
        let variables = st.mirror.entries.len() + prepared.variables.len();
        let limit = self.limits.max_variables_per_session;
        if variables > limit {
            return Err(full("variables", variables, limit));
        }
        let factors = (st.mirror.live_factors.len() + prepared.factors.len())
            .saturating_sub(prepared.remove.len());
        let limit = self.limits.max_factors_per_session;
        if factors > limit {
            return Err(full("factors", factors, limit));
        }
        Ok(())
    }
}
