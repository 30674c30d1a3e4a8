//! A session solve's [`solver::Budget`]: what stops it at the solver's checkpoints (every few
//! dozen factors of a linearisation or evaluation, before each factorisation), not only between
//! iterations, where one iteration over costly user-defined factors may take a minute.

use std::cell::Cell;
use std::ops::ControlFlow;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use super::Session;
use crate::solver;

/// Stops a session's solve when the session is cancelled or deleted (its `cancel` flag), when
/// the pool shuts down, or when the solve has spent `limits.max_solve_ms` (counting the turns an
/// earlier preempted part of it held). Preemption is not here: it stays between iterations
/// (`solve_once`), where a solve that gives its worker up resumes cleanly in a later turn.
pub(super) struct SolveBudget<'a> {
    session: &'a Session,
    start: Instant,
    /// Time this solve spent in earlier turns (it was preempted).
    carried: Duration,
    max_solve: Duration,
    /// Set when the time limit stopped the solve (not a cancellation): `last_error` says so.
    timed_out: Cell<bool>,
}

impl<'a> SolveBudget<'a> {
    pub(super) fn new(session: &'a Session, start: Instant, carried: Duration) -> Self {
        Self {
            session,
            start,
            carried,
            max_solve: Duration::from_millis(session.limits.max_solve_ms),
            timed_out: Cell::new(false),
        }
    }

    fn spent(&self) -> Duration {
        self.carried + self.start.elapsed()
    }

    pub(super) fn timed_out(&self) -> bool {
        self.timed_out.get()
    }
}

/// A consolidation the session asked for once it rested: it yields to the stream, stopping at
/// its next checkpoint once a batch after `sequence` is accepted (it then decides nothing, see
/// `outliers::consolidate`, and runs again at the next rest).
pub(super) struct YieldToBatches<'a> {
    pub(super) budget: &'a SolveBudget<'a>,
    pub(super) sequence: u64,
}

impl solver::Budget for YieldToBatches<'_> {
    fn checkpoint(&self) -> ControlFlow<()> {
        if *self.budget.session.accepted.borrow() > self.sequence {
            return ControlFlow::Break(());
        }
        self.budget.checkpoint()
    }

    fn remaining(&self) -> Option<Duration> {
        self.budget.remaining()
    }
}

impl solver::Budget for SolveBudget<'_> {
    fn checkpoint(&self) -> ControlFlow<()> {
        if self.session.cancel.load(Ordering::SeqCst) || self.session.pool.is_stopping() {
            return ControlFlow::Break(());
        }
        if self.spent() >= self.max_solve {
            self.timed_out.set(true);
            return ControlFlow::Break(());
        }
        ControlFlow::Continue(())
    }

    /// A factorisation predicted to outlast the time left is not started.
    fn remaining(&self) -> Option<Duration> {
        Some(self.max_solve.saturating_sub(self.spent()))
    }
}
