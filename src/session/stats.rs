//! What a session reports about itself: its settings, its counters and an estimate of the
//! memory it holds.

use super::engine::Engine;
use super::{Session, State};
use crate::api::wire::{CreateSession, FactorId, SessionInfo, SessionStats};
use crate::problem::Key;

impl Session {
    pub fn info(&self) -> SessionInfo {
        let st = self.lock();
        SessionInfo {
            session: self.name.clone(),
            kind: self.kind.name.into(),
            options: st.options.clone(),
            auto_optimize: st.auto,
            factor_types: self.factor_types().names().to_vec(),
            instance: None,
            ros2: self.ros2_binding().cloned().map(Box::new),
            max_update_ms: st.latency.as_ref().map(|l| l.max_update_ms),
        }
    }

    /// The creation request that builds this session again, empty, as it is configured now:
    /// its options and policy, every factor type it holds (also those declared after its
    /// creation), its ROS 2 binding, robots, outlier policy and latency budget. Journalled as
    /// its creation record, and what a ROS 2 `reset` creates again.
    pub fn creation_record(&self) -> CreateSession {
        let info = self.info();
        CreateSession {
            session: Some(self.name.clone()),
            kind: info.kind,
            options: Some(info.options.into()),
            auto_optimize: info.auto_optimize,
            factor_types: self.factor_types().definitions(),
            ros2: info.ros2,
            robots: self.robots_options(),
            outliers: self.outlier_policy(),
            max_update_ms: info.max_update_ms,
        }
    }

    pub fn stats(&self) -> SessionStats {
        let st = self.lock();
        let mut stats = SessionStats {
            session: self.name.clone(),
            kind: self.kind.name.into(),
            sequence: st.mirror.sequence,
            solved_sequence: st.results.solved_sequence,
            num_variables: st.mirror.entries.len(),
            num_factors: st.mirror.live_factors.len(),
            pending_batches: st.schedule.queued_batches(),
            solving: st.schedule.phase.is_solving(),
            solves: st.results.solves,
            skipped_solves: st.results.skipped_solves,
            chi2: st.results.chi2,
            converged: st.results.converged,
            auto_optimize: st.auto,
            options: st.options.clone(),
            last_error: self.last_error_locked(&st),
            last_summary: st.results.last_summary.clone(),
            recovering: self.is_recovering(),
            corrupt: self.corruption().is_some(),
            factor_types: self.factor_types().names().to_vec(),
            memory_bytes: self.memory_bytes_locked(&st),
            instance: None,
            ros2: self.ros2_binding().cloned().map(Box::new),
            latency: st
                .latency
                .as_ref()
                .map(|l| Box::new(l.report(st.results.solved_sequence))),
        };
        drop(st);
        if let Engine::Window(window) = &self.engine {
            let progress = window.progress.lock().unwrap_or_else(|p| p.into_inner());
            progress.fill(&mut stats);
        }
        stats
    }

    /// Why the last solve failed, or why the session is damaged (see `last_error_locked`):
    /// one field, for the request path, without building the whole [`Session::stats`].
    pub fn last_error(&self) -> Option<String> {
        self.last_error_locked(&self.lock())
    }

    /// The newest batch sequence a solve has reflected.
    pub fn solved_sequence(&self) -> u64 {
        self.lock().results.solved_sequence
    }

    /// Why the last solve failed, or why the session is damaged: a damaged recovery outranks
    /// solve errors, and a later solve does not clear it.
    pub(super) fn last_error_locked(&self, st: &State) -> Option<String> {
        self.corruption()
            .or(st.results.last_error.as_ref())
            .cloned()
    }

    /// Estimated bytes this session holds: the estimate clients read, the problem (variables,
    /// factors with their square-root information), queued batches, the wire copies kept for
    /// snapshots and its compiled factor types. An estimate from sizes, not an allocator count.
    pub fn memory_bytes(&self) -> usize {
        let st = self.lock();
        self.memory_bytes_locked(&st)
    }

    pub(super) fn memory_bytes_locked(&self, st: &State) -> usize {
        // Every term is O(1): counts and sums kept as the session changes.
        use std::mem::size_of;
        const NODE: usize = 48; // map/set node and allocation overhead
        let mirror = st.mirror.bytes();
        let factors = st.mirror.live_factors.len() * (size_of::<FactorId>() + NODE)
            + st.mirror.edges.len() * (size_of::<[Key; 2]>() + NODE)
            + st.model.factor_ids.len() * size_of::<FactorId>();
        // While a worker has the problem and its engine, their size when last here.
        let problem = st.model.memory_bytes();
        let marginals = match &self.engine {
            Engine::Graph(graph) => graph
                .marginals_bytes
                .load(std::sync::atomic::Ordering::Relaxed)
                as usize,
            // The window itself is small and bounded; the smoothed trajectory grows.
            Engine::Window(w) => {
                let kept = w.smoothed.lock().unwrap_or_else(|p| p.into_inner()).len();
                kept * std::mem::size_of::<super::engine::SmoothedKeyframe>()
            }
        };
        let producers = st.producers.bytes();
        let history = self
            .history
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .bytes();
        mirror
            + factors
            + self.unread_event_bytes()
            + problem
            + marginals
            + producers
            + history
            + self.durable_memory_bytes()
            + self.factor_type_bytes()
    }

    /// What its factor types hold, each counted in full (also when other sessions share it).
    pub fn factor_type_bytes(&self) -> usize {
        self.factor_types().bytes()
    }
}
