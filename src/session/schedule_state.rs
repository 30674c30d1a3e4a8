//! When a session's next solve runs, as a state machine: every change of the solve scheduling
//! goes through one of the transitions below, the only place its state is written.
//!
//! The phase says where the problem is and whether something waits for a solve; two flags are
//! orthogonal to it: the auto-optimise timer (armed or not, in any phase) and deletion (a
//! deleted session is never queued again, but a running solve runs to its next checkpoint).
//!
//! ```text
//!          mark_dirty, force          queue            start
//!   Idle ───────────────────▶ Waiting ──────▶ Queued ──────▶ Solving
//!     ▲                        ▲   ▲            │               │
//!     │                        │   └─ refused ──┘               │
//!     │                        └─────── finish (dirty) ─────────┤
//!     └──────────────────────────────── finish (clean) ─────────┘
//!
//!   Idle, Waiting ── lend ──▶ Lent ── give_back ──▶ Idle (clean) or Waiting (dirty)
//! ```
//!
//! | from             | transition            | to                                      |
//! |------------------|-----------------------|-----------------------------------------|
//! | Idle             | `mark_dirty`, `force` | Waiting{forced}                         |
//! | Waiting          | `queue`               | Queued (only when [`SolveSchedule::ready`]) |
//! | Queued           | `refused`             | Waiting (the pool is shutting down)     |
//! | Queued           | `start`               | Solving{next: Clean}, or Waiting if deleted |
//! | Solving{next}    | `finish`              | Idle if next is Clean, else Waiting     |
//! | Idle, Waiting    | `lend`                | Lent{next: what was owed}               |
//! | Lent{next}       | `give_back`           | Idle if next is Clean, else Waiting     |
//! | the others       | `mark_dirty`, `force` | same phase, owing a (forced) solve      |
//!
//! Any other transition is a bug: a debug assertion, and nothing changes in release builds.
//!
//! `mark_dirty` (something a solve could improve arrived) and `force` (a solve was asked for:
//! `optimize`, a preempted solve's next turn, a polish) keep Queued, Solving and Lent where
//! they are, recording in `next` what the phase after them owes. `forced` is only meaningful
//! while something is dirty, so it lives inside the phases that are.

/// Whether changes wait for a solve.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Demand {
    /// Nothing a solve could improve arrived.
    Clean,
    /// Something did; `forced`: a solve was asked for, and runs whatever the policy.
    Dirty { forced: bool },
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Phase {
    /// Nothing changed since the last solve; the problem is here.
    Idle,
    /// Changes wait for the policy (a timer, a factor count, `optimize` under `manual`) or for
    /// a pool that refused the solve; the problem is here.
    Waiting { forced: bool },
    /// Submitted to the pool; the problem is here until the worker takes it.
    Queued { forced: bool },
    /// The problem is on a worker; `next`: what arrived meanwhile.
    Solving { next: Demand },
    /// The problem is out for a factorisation (marginals): no solve takes it meanwhile.
    Lent { next: Demand },
}

impl Demand {
    fn with(self, forced: bool) -> Demand {
        match self {
            Demand::Clean => Demand::Dirty { forced },
            Demand::Dirty { forced: was } => Demand::Dirty {
                forced: was || forced,
            },
        }
    }

    /// The phase a session returns to when the problem comes back with this owed.
    fn at_rest(self) -> Phase {
        match self {
            Demand::Clean => Phase::Idle,
            Demand::Dirty { forced } => Phase::Waiting { forced },
        }
    }
}

/// The solve scheduling of one session: its phase, the timer and deletion.
#[derive(Debug)]
pub(super) struct SolveSchedule {
    phase: Phase,
    timer_armed: bool,
    deleted: bool,
}

impl Default for SolveSchedule {
    fn default() -> Self {
        SolveSchedule {
            phase: Phase::Idle,
            timer_armed: false,
            deleted: false,
        }
    }
}

impl SolveSchedule {
    #[cfg(test)]
    pub(super) fn phase(&self) -> Phase {
        self.phase
    }

    /// Changed since the last solve in a way a solve could improve.
    pub(super) fn is_dirty(&self) -> bool {
        match self.phase {
            Phase::Idle => false,
            Phase::Waiting { .. } | Phase::Queued { .. } => true,
            Phase::Solving { next } | Phase::Lent { next } => next != Demand::Clean,
        }
    }

    /// A solve is running on a worker.
    pub(super) fn is_solving(&self) -> bool {
        matches!(self.phase, Phase::Solving { .. })
    }

    /// Queued on or running in the pool, or the problem is out: nothing may queue a solve.
    pub(super) fn is_scheduled(&self) -> bool {
        matches!(
            self.phase,
            Phase::Queued { .. } | Phase::Solving { .. } | Phase::Lent { .. }
        )
    }

    /// The problem is here and no solve is queued for it (a polish may start).
    pub(super) fn is_at_rest(&self) -> bool {
        !self.deleted && matches!(self.phase, Phase::Idle | Phase::Waiting { .. })
    }

    /// A solve is coming without anyone asking for it: one is queued, running, or waiting for
    /// the problem to come back, or the timer is armed.
    pub(super) fn solve_coming(&self) -> bool {
        self.is_scheduled() || self.timer_armed
    }

    pub(super) fn is_deleted(&self) -> bool {
        self.deleted
    }

    /// Whether a solve may be queued now (changes wait, nothing holds the problem, not
    /// deleted), and if so whether it was asked for.
    pub(super) fn ready(&self) -> Option<bool> {
        match self.phase {
            Phase::Waiting { forced } if !self.deleted => Some(forced),
            _ => None,
        }
    }

    /// Something a solve could improve arrived.
    pub(super) fn mark_dirty(&mut self) {
        self.owe(false);
    }

    /// A solve was asked for: it runs whatever the policy.
    pub(super) fn force(&mut self) {
        self.owe(true);
    }

    fn owe(&mut self, forced: bool) {
        self.phase = match self.phase {
            Phase::Idle => Phase::Waiting { forced },
            Phase::Waiting { forced: was } => Phase::Waiting {
                forced: was || forced,
            },
            Phase::Queued { forced: was } => Phase::Queued {
                forced: was || forced,
            },
            Phase::Solving { next } => Phase::Solving {
                next: next.with(forced),
            },
            Phase::Lent { next } => Phase::Lent {
                next: next.with(forced),
            },
        };
    }

    /// The solve was submitted to the pool (only from [`ready`](Self::ready)).
    pub(super) fn queue(&mut self) {
        let Phase::Waiting { forced } = self.phase else {
            debug_assert!(false, "queue from {:?}", self.phase);
            return;
        };
        self.phase = Phase::Queued { forced };
    }

    /// The pool refused the solve (it is shutting down): the changes wait again.
    pub(super) fn refused(&mut self) {
        let Phase::Queued { forced } = self.phase else {
            debug_assert!(false, "refused from {:?}", self.phase);
            return;
        };
        self.phase = Phase::Waiting { forced };
    }

    /// A worker takes the queued solve: returns whether it was asked for, or `None` when the
    /// session was deleted meanwhile (nothing runs; the changes wait for nobody).
    pub(super) fn start(&mut self) -> Option<bool> {
        let Phase::Queued { forced } = self.phase else {
            debug_assert!(false, "start from {:?}", self.phase);
            return None;
        };
        if self.deleted {
            self.phase = Phase::Waiting { forced };
            return None;
        }
        self.phase = Phase::Solving {
            next: Demand::Clean,
        };
        Some(forced)
    }

    /// The running solve finished and handed the problem back.
    pub(super) fn finish(&mut self) {
        let Phase::Solving { next } = self.phase else {
            debug_assert!(false, "finish from {:?}", self.phase);
            return;
        };
        self.phase = next.at_rest();
    }

    /// Takes the problem out for a factorisation if it is here and no solve is queued; returns
    /// whether it did.
    pub(super) fn lend(&mut self) -> bool {
        let next = match self.phase {
            Phase::Idle => Demand::Clean,
            Phase::Waiting { forced } => Demand::Dirty { forced },
            _ => return false,
        };
        self.phase = Phase::Lent { next };
        true
    }

    /// The lent problem is back.
    pub(super) fn give_back(&mut self) {
        let Phase::Lent { next } = self.phase else {
            debug_assert!(false, "give_back from {:?}", self.phase);
            return;
        };
        self.phase = next.at_rest();
    }

    /// Arms the auto-optimise timer unless it is armed; returns whether it did.
    pub(super) fn arm_timer(&mut self) -> bool {
        !std::mem::replace(&mut self.timer_armed, true)
    }

    pub(super) fn timer_fired(&mut self) {
        self.timer_armed = false;
    }

    /// No solve is queued for the session again.
    pub(super) fn delete(&mut self) {
        self.deleted = true;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(phase: Phase) -> SolveSchedule {
        SolveSchedule {
            phase,
            ..SolveSchedule::default()
        }
    }

    const DIRTY: Demand = Demand::Dirty { forced: false };
    const FORCED: Demand = Demand::Dirty { forced: true };

    #[test]
    fn a_new_session_is_idle_and_clean() {
        let s = SolveSchedule::default();
        assert_eq!(s.phase(), Phase::Idle);
        assert!(!s.is_dirty() && !s.is_scheduled() && !s.is_solving() && !s.solve_coming());
        assert!(s.is_at_rest() && !s.is_deleted());
        assert_eq!(s.ready(), None);
    }

    #[test]
    fn changes_and_requests_accumulate_in_every_phase() {
        let cases = [
            (
                Phase::Idle,
                Phase::Waiting { forced: false },
                Phase::Waiting { forced: true },
            ),
            (
                Phase::Waiting { forced: false },
                Phase::Waiting { forced: false },
                Phase::Waiting { forced: true },
            ),
            (
                Phase::Waiting { forced: true },
                Phase::Waiting { forced: true },
                Phase::Waiting { forced: true },
            ),
            (
                Phase::Queued { forced: false },
                Phase::Queued { forced: false },
                Phase::Queued { forced: true },
            ),
            (
                Phase::Solving {
                    next: Demand::Clean,
                },
                Phase::Solving { next: DIRTY },
                Phase::Solving { next: FORCED },
            ),
            (
                Phase::Solving { next: FORCED },
                Phase::Solving { next: FORCED },
                Phase::Solving { next: FORCED },
            ),
            (
                Phase::Lent {
                    next: Demand::Clean,
                },
                Phase::Lent { next: DIRTY },
                Phase::Lent { next: FORCED },
            ),
        ];
        for (from, dirty, forced) in cases {
            let mut s = at(from);
            s.mark_dirty();
            assert_eq!(s.phase(), dirty, "mark_dirty from {from:?}");
            assert!(s.is_dirty());
            let mut s = at(from);
            s.force();
            assert_eq!(s.phase(), forced, "force from {from:?}");
            assert!(s.is_dirty());
        }
    }

    #[test]
    fn waiting_changes_are_queued_started_and_finished() {
        let mut s = SolveSchedule::default();
        s.force();
        assert_eq!(s.ready(), Some(true));
        s.queue();
        assert_eq!(s.phase(), Phase::Queued { forced: true });
        assert!(s.is_scheduled() && s.solve_coming() && !s.is_solving() && !s.is_at_rest());
        assert_eq!(s.ready(), None);
        assert_eq!(s.start(), Some(true));
        assert_eq!(
            s.phase(),
            Phase::Solving {
                next: Demand::Clean
            }
        );
        assert!(s.is_solving() && s.is_scheduled() && !s.is_dirty());
        s.finish();
        assert_eq!(s.phase(), Phase::Idle);
        assert!(!s.is_scheduled() && s.is_at_rest());
    }

    #[test]
    fn a_solve_that_saw_changes_arrive_leaves_them_waiting() {
        for next in [DIRTY, FORCED] {
            let mut s = at(Phase::Solving { next });
            s.finish();
            let Demand::Dirty { forced } = next else {
                unreachable!()
            };
            assert_eq!(s.phase(), Phase::Waiting { forced });
            assert_eq!(s.ready(), Some(forced));
        }
    }

    #[test]
    fn a_refused_solve_waits_again() {
        let mut s = at(Phase::Queued { forced: false });
        s.refused();
        assert_eq!(s.phase(), Phase::Waiting { forced: false });
        assert_eq!(s.ready(), Some(false));
    }

    #[test]
    fn a_deleted_session_is_not_queued_and_its_queued_solve_does_not_start() {
        let mut s = at(Phase::Waiting { forced: true });
        s.delete();
        assert!(s.is_deleted() && !s.is_at_rest());
        assert_eq!(s.ready(), None);
        let mut s = at(Phase::Queued { forced: true });
        s.delete();
        assert_eq!(s.start(), None);
        assert_eq!(s.phase(), Phase::Waiting { forced: true });
        assert_eq!(s.ready(), None);
    }

    #[test]
    fn the_problem_is_lent_only_when_here_and_unqueued() {
        for (from, lent) in [
            (Phase::Idle, Some(Demand::Clean)),
            (Phase::Waiting { forced: true }, Some(FORCED)),
            (Phase::Queued { forced: false }, None),
            (
                Phase::Solving {
                    next: Demand::Clean,
                },
                None,
            ),
            (
                Phase::Lent {
                    next: Demand::Clean,
                },
                None,
            ),
        ] {
            let mut s = at(from);
            assert_eq!(s.lend(), lent.is_some(), "{from:?}");
            match lent {
                Some(next) => {
                    assert_eq!(s.phase(), Phase::Lent { next });
                    assert!(s.is_scheduled() && !s.is_solving());
                    assert_eq!(s.ready(), None);
                }
                None => assert_eq!(s.phase(), from),
            }
        }
    }

    #[test]
    fn a_lent_problem_comes_back_to_what_arrived_meanwhile() {
        for (next, back) in [
            (Demand::Clean, Phase::Idle),
            (DIRTY, Phase::Waiting { forced: false }),
            (FORCED, Phase::Waiting { forced: true }),
        ] {
            let mut s = at(Phase::Lent { next });
            s.give_back();
            assert_eq!(s.phase(), back);
        }
    }

    #[test]
    fn the_timer_is_armed_once_and_counts_as_a_coming_solve() {
        let mut s = at(Phase::Waiting { forced: false });
        assert!(!s.solve_coming());
        assert!(s.arm_timer());
        assert!(!s.arm_timer(), "already armed");
        assert!(s.solve_coming());
        assert_eq!(
            s.ready(),
            Some(false),
            "the timer does not hold the problem"
        );
        s.timer_fired();
        assert!(!s.solve_coming());
        assert!(s.arm_timer());
    }

    #[test]
    #[cfg(debug_assertions)]
    #[should_panic(expected = "finish from Idle")]
    fn an_illegal_transition_is_a_bug() {
        SolveSchedule::default().finish();
    }

    #[test]
    fn an_illegal_transition_changes_nothing_in_release() {
        if cfg!(debug_assertions) {
            return;
        }
        for from in [Phase::Idle, Phase::Queued { forced: false }] {
            let mut s = at(from);
            s.finish();
            s.give_back();
            assert_eq!(s.phase(), from);
        }
        let mut s = SolveSchedule::default();
        s.queue();
        s.refused();
        assert_eq!(s.start(), None);
        assert_eq!(s.phase(), Phase::Idle);
    }
}
