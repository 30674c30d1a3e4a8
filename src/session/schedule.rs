//! When solves run: the auto-optimise policy, explicit requests, waiting for a solve, and
//! stopping one.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use super::{Session, State};
use crate::api::wire::AutoOptimize;
use crate::api::ServiceError;

impl Session {
    /// Queues a solve if changes wait and the auto-optimise policy (or a request) says so.
    pub(super) fn maybe_schedule(self: &Arc<Self>, st: &mut State) {
        let Some(forced) = st.schedule.phase.ready() else {
            return;
        };
        if forced {
            return self.schedule(st);
        }
        match st.auto {
            AutoOptimize::EveryBatch {} => self.schedule(st),
            AutoOptimize::EveryNFactors { factors } => {
                if st.schedule.factors_since_solve >= factors {
                    self.schedule(st)
                }
            }
            AutoOptimize::EveryMs { milliseconds } => {
                if st.schedule.phase.arm_timer() {
                    let session = Arc::clone(self);
                    self.runtime.spawn(async move {
                        tokio::time::sleep(Duration::from_millis(milliseconds)).await;
                        let mut st = session.lock();
                        st.schedule.phase.timer_fired();
                        if st.schedule.phase.ready().is_some() {
                            session.schedule(&mut st);
                        }
                    });
                }
            }
            AutoOptimize::Manual {} => {}
        }
    }

    /// Submits a solve to the pool (changes wait: see [`SolveSchedule::ready`](super::schedule_state::SolveSchedule::ready)).
    pub(super) fn schedule(self: &Arc<Self>, st: &mut State) {
        st.schedule.phase.queue();
        let session = Arc::clone(self);
        if !self.pool.submit(Box::new(move || session.solve_once())) {
            st.schedule.phase.refused(); // the pool is shutting down
        }
    }

    /// Asks for a solve now, whatever the policy. Returns the sequence it will reflect and the
    /// number the solve will have (for [`Session::wait_solve`]).
    pub fn optimize_now(self: &Arc<Self>) -> Result<(u64, u64), ServiceError> {
        let mut st = self.lock();
        if st.schedule.phase.is_deleted() {
            return Err(self.gone());
        }
        st.schedule.phase.force();
        st.schedule.asked = true;
        st.results.converged = false;
        // Asked for explicitly: the whole problem, not only the region the last updates reach
        // (region solves stop within their tolerance of the optimum; this one goes all the way).
        st.schedule.structural = true;
        if !st.schedule.phase.is_scheduled() {
            self.schedule(&mut st);
        }
        // A running solve started before this request; the one asked for is the next.
        Ok((st.mirror.sequence, st.results.solves + 1))
    }

    /// Waits until a solve reflecting `sequence` finished, at most `timeout`.
    pub async fn wait_solved(&self, sequence: u64, timeout: Duration) -> bool {
        let mut rx = self.solved.subscribe();
        tokio::time::timeout(timeout, rx.wait_for(|s| *s >= sequence))
            .await
            .is_ok_and(|r| r.is_ok())
    }

    /// Waits until solve number `solve` finished, at most `timeout`.
    pub async fn wait_solve(&self, solve: u64, timeout: Duration) -> bool {
        let mut rx = self.completed.subscribe();
        tokio::time::timeout(timeout, rx.wait_for(|n| *n >= solve))
            .await
            .is_ok_and(|r| r.is_ok())
    }

    /// Wakes every waiter (the session is going away or the service is stopping).
    pub(crate) fn release_waiters(&self) {
        self.solved.send_replace(u64::MAX);
        self.answered.send_replace(u64::MAX);
        self.completed.send_replace(u64::MAX);
    }

    pub fn set_auto_optimize(self: &Arc<Self>, auto: AutoOptimize) -> Result<(), ServiceError> {
        if let AutoOptimize::EveryNFactors { factors: 0 } = auto {
            return Err(ServiceError::bad_request(
                "invalid_value",
                "factors",
                "every_n_factors needs factors >= 1",
            ));
        }
        if let AutoOptimize::EveryMs { milliseconds: 0 } = auto {
            return Err(ServiceError::bad_request(
                "invalid_value",
                "milliseconds",
                "every_ms needs milliseconds >= 1",
            ));
        }
        let mut st = self.lock();
        if st.schedule.phase.is_deleted() {
            return Err(self.gone());
        }
        self.journal_auto_optimize(auto)?;
        st.auto = auto;
        self.maybe_schedule(&mut st);
        Ok(())
    }

    /// Stops the running solve at its next budget checkpoint (see `solve_budget`: within a few
    /// dozen factors of work, not at the end of the iteration); returns whether one was running.
    pub fn cancel(&self) -> bool {
        let st = self.lock();
        let solving = st.schedule.phase.is_solving();
        if solving {
            self.cancel.store(true, Ordering::SeqCst);
        }
        solving
    }

    /// No solve is scheduled for a deleted session again (`maybe_schedule`, `take_work` and the
    /// polish timer check `deleted`), and the running one stops at its next checkpoint.
    pub(crate) fn mark_deleted(&self) {
        let mut st = self.lock();
        st.schedule.phase.delete();
        self.cancel.store(true, Ordering::SeqCst);
        drop(st);
        self.release_waiters();
    }

    /// Schedules a polish step (an engine update towards convergence, bounded in what it
    /// refactors) if no batch arrives within [`POLISH_AFTER_IDLE`]: a stream's next update
    /// never waits behind a polish, and a batch that arrives later waits for one step at most.
    pub(super) fn polish_when_idle(self: &Arc<Self>, sequence: u64) {
        let session = Arc::clone(self);
        self.runtime.spawn(async move {
            tokio::time::sleep(POLISH_AFTER_IDLE).await;
            let mut st = session.lock();
            if st.mirror.sequence == sequence && st.schedule.phase.is_at_rest() {
                st.schedule.phase.force();
                session.schedule(&mut st);
            }
        });
    }

    /// Asks for a bundle adjustment's restart from its given values (`bundle`) if one is due
    /// and no batch arrives within [`RESTART_AFTER_IDLE`]: once a stream rests, its estimate
    /// reaches the batch solve of what was sent without the client asking. The restart gives
    /// way to the next batch (it stops at its next checkpoint, changes nothing, and runs at the
    /// next rest).
    pub(super) fn restart_when_idle(self: &Arc<Self>, st: &State) {
        if !restart_due(st) {
            return;
        }
        let (session, sequence) = (Arc::clone(self), st.mirror.sequence);
        self.runtime.spawn(async move {
            tokio::time::sleep(RESTART_AFTER_IDLE).await;
            let mut st = session.lock();
            if st.mirror.sequence == sequence && st.schedule.phase.is_at_rest() && restart_due(&st)
            {
                st.schedule.restart_when_idle = true;
                st.schedule.phase.force();
                session.schedule(&mut st);
            }
        });
    }

    /// Asks for a consolidation if no batch arrives within [`CONSOLIDATE_AFTER_IDLE`]: the
    /// gate's decisions since the last one are then checked together, off the stream's path.
    pub(super) fn consolidate_when_idle(self: &Arc<Self>, sequence: u64) {
        let session = Arc::clone(self);
        self.runtime.spawn(async move {
            tokio::time::sleep(CONSOLIDATE_AFTER_IDLE).await;
            let mut st = session.lock();
            if st.mirror.sequence == sequence
                && st.schedule.phase.is_at_rest()
                && st.outliers.consolidation_due()
            {
                st.outliers.requested = true;
                st.schedule.phase.force();
                session.schedule(&mut st);
            }
        });
    }
}

/// How long a session must be idle before it polishes its estimate.
const POLISH_AFTER_IDLE: std::time::Duration = std::time::Duration::from_millis(20);

/// How long a session must be idle before the gate's decisions are consolidated (a batch solve
/// with graduated non-convexity: tens of milliseconds to seconds, so not between a stream's
/// batches).
const CONSOLIDATE_AFTER_IDLE: std::time::Duration = std::time::Duration::from_millis(500);

/// Values were given since the last restart of a bundle adjustment whose solves are not left to
/// its client (the `manual` policy).
fn restart_due(st: &State) -> bool {
    let given = st.model.index.as_ref().is_some_and(|i| i.given.changed());
    given && !matches!(st.auto, AutoOptimize::Manual {})
}

/// How long a bundle adjustment must be idle before it restarts from its given values (a batch
/// solve: tenths of seconds to minutes, so not between a stream's batches).
const RESTART_AFTER_IDLE: std::time::Duration = std::time::Duration::from_millis(500);
