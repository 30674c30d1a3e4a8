//! A session's solve on a pool worker: take the problem out of the state, re-solve it (as far as
//! the updates reach, see `incremental`), hand it back, apply what arrived meanwhile, publish the
//! estimate changes and the Summary, and reschedule if needed.

use std::ops::ControlFlow;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Instant;

use super::background_priority::{self, Background};
use super::incremental::{self, IncrementalSolver};
use super::mirror::MovedValues;
use super::outliers::{self, DecidedBy, OutlierOutcome, OutlierWork};
use super::provisional::LandingRefresh;
use super::solve_budget::{SolveBudget, YieldToBatches};
use super::{Session, State};
use crate::api::wire::AutoOptimize;
use crate::api::wire::{Estimate, FactorId, SessionEvent};
use crate::api::ErrorKind;
use crate::api::ServiceError;
use crate::problem::{Key, Problem};
use crate::runtime::pool::TIME_SLICE;
use crate::solver::{self, Budget as _, SolverOptions};

/// What a solve takes out of the session state (the problem moves to the worker). `bundle`
/// reads the problem, its options and what the solve was asked for.
pub(super) struct SolveWork {
    pub(super) problem: Problem,
    pub(super) index: IncrementalSolver,
    pub(super) options: SolverOptions,
    pub(super) sequence: u64,
    pub(super) solve_number: u64,
    seeds: Vec<usize>,
    structural: bool,
    chi2: Option<f64>,
    pub(super) debt: f64,
    gauge: Vec<Key>,
    /// A solve the client asked for, or a polish: an engine update runs to convergence.
    pub(super) tight: bool,
    /// The client asked for this solve (`optimize`): a bundle adjustment also restarts from
    /// its given values (`bundle`).
    pub(super) asked: bool,
    /// A bundle adjustment at rest restarts from its given values, yielding to batches.
    pub(super) restart_when_idle: bool,
    /// The session's `max_iterations` while a bundle adjustment's solve runs capped (`bundle`).
    pub(super) uncapped: Option<usize>,
    /// A consolidation asked for once the session rested (not a full solve): it yields to
    /// batches that arrive meanwhile.
    yields: bool,
    /// Possibly wrong closures this solve decides (`session::outliers`): what it took, what it
    /// decided, the gate's entries (appended to the problem, ids in order) and, when it
    /// consolidates, the factors' ids (candidates enter and leave the problem).
    outliers: Option<OutlierWork>,
    outcome: OutlierOutcome,
    entered: Vec<FactorId>,
    factor_ids: Option<Vec<FactorId>>,
}

impl Session {
    /// Starts the queued solve: takes the problem and what it needs out of the state, or
    /// `None` when the session was deleted since (see `SolveSchedule::start`).
    fn take_work(&self) -> Option<SolveWork> {
        let mut st = self.lock();
        let forced = st.schedule.phase.start()?;
        // Tight (to convergence): a polish, or a solve the client asked for with nothing new
        // (or under the manual policy, where no polish follows). New factors otherwise take
        // the request-path thresholds and a polish follows.
        let tight =
            forced && (st.schedule.seeds.is_empty() || matches!(st.auto, AutoOptimize::Manual {}));
        st.schedule.factors_since_solve = 0;
        st.results.solves += 1;
        self.cancel.store(false, Ordering::SeqCst);
        // A full solve decides every candidate again (so does the first after the session
        // rested from gate decisions); a streamed one gates the pending ones.
        let full = st.schedule.structural || st.results.solves == 1 || st.results.chi2.is_none();
        let requested = std::mem::take(&mut st.outliers.requested);
        let consolidate = full || requested;
        let outliers = (!st.outliers.is_empty()).then(|| st.outliers.take_for_solve(consolidate));
        let factor_ids = outliers
            .as_ref()
            .filter(|o| o.consolidate)
            .map(|_| std::mem::take(&mut st.model.factor_ids));
        let (problem, mut index) = st.model.take();
        // With a budget this solve is off the request path already (`provisional`).
        index.off_request_path = st.latency.is_some();
        Some(SolveWork {
            problem,
            index,
            options: st.options.clone(),
            // Batches are applied as they come while the problem is here: it reflects them all.
            sequence: st.mirror.sequence,
            solve_number: st.results.solves,
            seeds: std::mem::take(&mut st.schedule.seeds),
            structural: std::mem::replace(&mut st.schedule.structural, false),
            chi2: st.results.chi2,
            debt: st.schedule.region_debt,
            gauge: st.model.gauge.clone(),
            tight,
            asked: std::mem::take(&mut st.schedule.asked),
            restart_when_idle: std::mem::take(&mut st.schedule.restart_when_idle),
            uncapped: None,
            yields: requested && !full,
            outliers,
            outcome: OutlierOutcome::default(),
            entered: Vec::new(),
            factor_ids,
        })
    }

    /// What a solve's turn starts with: the time its preempted turns took, and, in a session
    /// with a latency budget (its solves are off the request path), the lower priority it
    /// computes at until it lands (see `background_priority`), taken outside the lock.
    fn solve_turn(&self) -> (std::time::Duration, Option<Background>) {
        let (carried, answered_provisionally) = {
            let st = self.lock();
            (st.schedule.carried, st.latency.is_some())
        };
        (
            carried,
            answered_provisionally.then(|| Background::enter(&self.runtime)),
        )
    }

    /// One solve on a pool worker: take the problem, optimise without the lock, hand it back,
    /// apply what arrived meanwhile, and reschedule if that needs another solve.
    pub(super) fn solve_once(self: Arc<Self>) {
        let Some(mut work) = self.take_work() else {
            return;
        };
        let _span = tracing::info_span!("session", session = %self.name, solve = work.solve_number)
            .entered();
        let start = Instant::now();
        let (carried, background) = self.solve_turn();
        let budget = SolveBudget::new(&self, start, carried);
        let (result, preempted) = self.run_solver(&mut work, &budget, start);
        let run = Run {
            sequence: work.sequence,
            solve_number: work.solve_number,
            start,
            carried,
            preempted,
            timed_out: budget.timed_out(),
        };
        report_finished(&result, start);
        // Encoded before the lock is taken: batches arriving meanwhile need it.
        let moved = match &result {
            Ok(r) => MovedValues::encode(&work.problem, r.moved.as_deref()),
            Err(_) => MovedValues::default(),
        };
        // The landing holds the session's lock, which the request path waits for: most of what
        // it moved goes into the mirror before, a slice per hold of the lock.
        drop(background);
        self.journal_barrier();
        let mut refresh = LandingRefresh::new(&moved, run.sequence);
        let mut st = self.refresh_before_landing(&mut refresh);
        let landing = Instant::now();
        self.cancel.store(false, Ordering::SeqCst);
        let polish = match result {
            Ok(resolved) => {
                self.publish_solved(&mut st, &run, resolved, &work.problem, refresh);
                // An engine update that left steps above the threshold polishes once the
                // session is idle, unless the client decides when solves run: counted from
                // when this solve is published and handed back (below), so the time a large
                // update spends there does not count as idle.
                work.index.polish && !matches!(st.auto, AutoOptimize::Manual {})
            }
            Err(e) => {
                self.publish_failed(&mut st, &run, e);
                false
            }
        };
        st.results.solved_sequence = st.results.solved_sequence.max(run.sequence);
        if let Some(latency) = st.latency.as_mut() {
            latency.solved_in(start.elapsed());
        }
        st.schedule.region_debt = work.debt;
        if let Some(ids) = work.factor_ids.take() {
            st.model.factor_ids = ids;
        }
        st.model.factor_ids.append(&mut work.entered);
        let consolidated = work.outliers.is_none()
            && work
                .outcome
                .decisions
                .first()
                .is_some_and(|d| d.by == DecidedBy::GraduatedNonConvexity);
        let outcome = std::mem::take(&mut work.outcome);
        if let Some(untouched) = work.outliers.take() {
            // Not decided (the solve failed before it got there): held as they were.
            st.outliers.give_back(untouched);
        }
        if let Some(decisions) = st.outliers.finish(outcome, consolidated, run.sequence) {
            self.emit(SessionEvent::Outliers {
                session: self.name.clone(),
                decisions,
            });
        }
        if st.outliers.consolidation_due() {
            self.consolidate_when_idle(st.mirror.sequence);
        }
        self.hand_back(&mut st, work.problem, work.index);
        self.answer_after_landing(&st);
        if polish {
            self.polish_when_idle(st.mirror.sequence);
        }
        self.restart_when_idle(&st);
        st.schedule.phase.finish();
        self.solved.send_replace(st.results.solved_sequence);
        self.completed
            .send_modify(|n| *n = (*n).max(run.solve_number));
        self.maybe_schedule(&mut st);
        drop(st);
        crate::runtime::metrics::observe_landing(landing.elapsed());
    }

    /// Runs the solver on `work` within `budget`, publishing each iteration; returns its
    /// result and whether it stopped to let other sessions' solves run (preempted).
    fn run_solver(
        &self,
        work: &mut SolveWork,
        budget: &SolveBudget,
        start: Instant,
    ) -> (Result<incremental::Resolved, solver::SolverError>, bool) {
        let (solve_number, sequence) = (work.solve_number, work.sequence);
        let mut preempted = false;
        // Threads beyond this worker's own come from idle workers of the pool, none while a
        // task waits: a solve never takes more cores than the pool lends it, and gives them back
        // (by yielding) at the first iteration that ends while another task waits. Only a
        // problem with variables to eliminate (bundle adjustment) splits its work: a pose
        // graph's solve runs on one thread and borrows nothing.
        // The options are this solve's copy (taken with the work): the lent count replaces the
        // asked one for it alone.
        let wanted = match work.options.threads {
            _ if work.problem.eliminate.is_empty() => 1,
            0 => self.pool.workers(),
            n => n,
        };
        let borrowed = self.pool.borrow_idle(wanted.saturating_sub(1));
        work.options.threads = 1 + borrowed.count();
        let lends = borrowed.count() > 0;
        let mut on_iteration = |report: &solver::IterationReport| {
            // Nothing is published of a batch before it is durable (see `journal_barrier`).
            // Both wait for what the request path holds (and the barrier may run the fdatasync
            // its batches wait for): at the worker's own priority, not the solve's.
            background_priority::foreground(|| {
                self.journal_barrier();
                self.emit(SessionEvent::Iteration {
                    session: self.name.clone(),
                    solve: solve_number,
                    sequence,
                    report: report.clone(),
                });
            });
            if budget.checkpoint().is_break() {
                return ControlFlow::Break(());
            }
            if self.pool.waiting() > 0 && (lends || start.elapsed() > TIME_SLICE) {
                preempted = true;
                return ControlFlow::Break(());
            }
            ControlFlow::Continue(())
        };
        let solve = std::panic::AssertUnwindSafe(|| {
            let resolved = self.solve(work, &mut on_iteration, budget)?;
            self.after_bundle_solve(work, resolved, &mut on_iteration, budget)
        });
        // A panic inside the solver is a bug; report it as a failed solve and keep the session.
        let result = std::panic::catch_unwind(solve)
            .unwrap_or_else(|_| Err(solver::SolverError::Internal("the solver panicked".into())));
        drop(borrowed);
        (result, preempted)
    }

    /// The solve itself: after additions only, an engine update or a re-solve of the region
    /// they reach; otherwise (or when the engine fails) the whole problem.
    fn solve(
        &self,
        work: &mut SolveWork,
        on_iteration: &mut dyn FnMut(&solver::IterationReport) -> ControlFlow<()>,
        budget: &SolveBudget,
    ) -> Result<incremental::Resolved, solver::SolverError> {
        if work.outliers.as_ref().is_some_and(|o| o.consolidate) {
            return self.consolidate(work, on_iteration, budget);
        }
        work.cap_bundle_iterations();
        let additions_only = !work.structural && work.solve_number > 1;
        if let Some(total) = work.chi2.filter(|_| additions_only) {
            let SolveWork {
                problem,
                index,
                options,
                gauge,
                tight,
                ..
            } = work;
            match index.update_engine(problem, total, *tight, options, gauge, on_iteration) {
                Some(Ok(resolved)) => return self.gate(work, resolved, on_iteration, budget),
                // The engine failed (an indeterminate update): solve in batch below.
                Some(Err(e)) => {
                    tracing::debug!("incremental update failed, solving in batch: {e}")
                }
                // After additions only, re-solve as far as they reach.
                None => {
                    return self.resolve_regions(
                        problem,
                        index,
                        &work.seeds,
                        total,
                        &mut work.debt,
                        options,
                        gauge,
                        on_iteration,
                        budget,
                    )
                }
            }
        }
        let SolveWork {
            problem,
            index,
            options,
            solve_number,
            debt,
            ..
        } = work;
        // Later solves warm-start from the current estimate; initialisation is for the first.
        *debt = 0.0;
        let solved = if *solve_number > 1 {
            index.solve_whole(problem, options, on_iteration, budget)
        } else {
            solver::optimize_within(problem, options, on_iteration, budget)
        };
        Ok(index.adopt_whole(problem, solved?))
    }

    /// Records a finished solve, refreshes the mirror from `problem` and publishes the
    /// estimate changes and the summary.
    fn publish_solved(
        &self,
        st: &mut State,
        run: &Run,
        resolved: incremental::Resolved,
        problem: &Problem,
        refresh: LandingRefresh<'_>,
    ) {
        let summary = resolved.summary;
        if summary.used.region_variables.is_none() {
            st.model.gauge = summary.used.gauge_fixed.clone();
        }
        let stopped = run.timed_out.then(|| {
            format!(
                "the solve stopped at the time limit of {} ms (limits.max_solve_ms) after {} iterations; the estimate is the best it reached",
                self.limits.max_solve_ms, summary.iterations
            )
        });
        st.results
            .solved(resolved.total_chi2, resolved.converged, stopped);
        // A preempted solve continues in its next turn (its time counts towards the limit); a
        // cancelled or timed-out one waits for news.
        if run.preempted && !run.timed_out {
            st.schedule.phase.force();
            st.schedule.carried = run.carried + run.start.elapsed();
        } else {
            st.schedule.carried = std::time::Duration::ZERO;
        }
        let changed = refresh.finish(st, problem);
        if !changed.is_empty() {
            self.emit(SessionEvent::Estimate(Estimate {
                session: self.name.clone(),
                sequence: run.sequence,
                variables: changed,
            }));
        }
        self.emit(SessionEvent::Summary {
            session: self.name.clone(),
            solve: run.solve_number,
            sequence: run.sequence,
            summary: Box::new(summary.clone()),
        });
        st.results.last_summary = Some(summary);
    }

    /// Records a failed solve and publishes its error; the mirror keeps the last good values.
    fn publish_failed(&self, st: &mut State, run: &Run, e: solver::SolverError) {
        // Whatever moved, the next solve starts from a clean slate.
        st.schedule.structural = true;
        // Stopped by the time limit before the first step: say which limit.
        let message = if run.timed_out {
            format!(
                "the solve stopped at the time limit of {} ms (limits.max_solve_ms): {e}",
                self.limits.max_solve_ms
            )
        } else {
            e.to_string()
        };
        st.results.failed(message.clone());
        self.emit(SessionEvent::Error {
            session: self.name.clone(),
            sequence: Some(run.sequence),
            error: ServiceError::new(ErrorKind::Invalid, "solve_failed", message).body,
            producer: None,
            producer_seq: None,
        });
    }
}

impl Session {
    /// After a streamed engine update: the pending candidates through the gate, and a second
    /// update that takes in those it let through (a batch solve if that update fails).
    fn gate(
        &self,
        work: &mut SolveWork,
        resolved: incremental::Resolved,
        on_iteration: &mut dyn FnMut(&solver::IterationReport) -> ControlFlow<()>,
        budget: &SolveBudget,
    ) -> Result<incremental::Resolved, solver::SolverError> {
        let Some(candidates) = work.outliers.take() else {
            return Ok(resolved);
        };
        let first = work.problem.factors().len();
        let summary = &resolved.summary;
        let scale = outliers::noise_scale(
            resolved.total_chi2,
            summary.num_residuals,
            summary.num_parameters,
        );
        let gated = outliers::gate(&mut work.problem, &work.index, candidates.held, scale);
        work.outcome = gated.outcome;
        work.entered = gated.entered;
        if work.entered.is_empty() {
            return Ok(resolved);
        }
        let problem = &mut work.problem;
        work.index.extend(problem, first);
        let entered_chi2 = solver::evaluate_chi2(&problem.factors()[first..], &problem.values)
            .unwrap_or(f64::INFINITY);
        let total = resolved.total_chi2 + entered_chi2;
        let again = work.index.update_engine(
            problem,
            total,
            work.tight,
            &work.options,
            &work.gauge,
            on_iteration,
        );
        match again {
            Some(Ok(again)) => {
                let moved = match (resolved.moved, again.moved) {
                    (Some(mut a), Some(b)) => {
                        a.extend(b);
                        a.sort_unstable();
                        a.dedup();
                        Some(a)
                    }
                    _ => None,
                };
                Ok(incremental::Resolved { moved, ..again })
            }
            _ => {
                let summary =
                    work.index
                        .solve_whole(problem, &work.options, on_iteration, budget)?;
                Ok(work.index.adopt_whole(problem, summary))
            }
        }
    }

    /// Every candidate decided again together (`outliers::consolidate`), then the engine
    /// built again at the answer. An interrupted consolidation decides nothing and leaves the
    /// problem as it found it, values included, so the engine still fits it.
    fn consolidate(
        &self,
        work: &mut SolveWork,
        on_iteration: &mut dyn FnMut(&solver::IterationReport) -> ControlFlow<()>,
        budget: &SolveBudget,
    ) -> Result<incremental::Resolved, solver::SolverError> {
        let candidates = work
            .outliers
            .take()
            .expect("consolidate is asked with candidates");
        let mut ids = work.factor_ids.take().expect("taken with the candidates");
        let before = work.problem.values.clone();
        let yielding = YieldToBatches {
            budget,
            sequence: work.sequence,
        };
        let budget: &dyn solver::Budget = if work.yields { &yielding } else { budget };
        let (solved, outcome) = outliers::consolidate(
            &mut work.problem,
            &mut ids,
            candidates,
            &work.options,
            on_iteration,
            budget,
        );
        work.factor_ids = Some(ids);
        let decided = !outcome.decisions.is_empty();
        work.outcome = outcome;
        if !decided {
            work.problem.values = before;
        } else {
            work.index.rebuild(&work.problem);
        }
        work.debt = 0.0;
        let summary = solved?;
        Ok(if decided {
            work.index.adopt_whole(&mut work.problem, summary)
        } else {
            // Undecided: the problem is as before, not at the optimum of anything new.
            incremental::Resolved {
                converged: false,
                ..incremental::Resolved::whole(summary)
            }
        })
    }
}

/// How a solve ran, for what it publishes.
struct Run {
    sequence: u64,
    solve_number: u64,
    start: Instant,
    /// Time it spent in earlier (preempted) turns.
    carried: std::time::Duration,
    preempted: bool,
    timed_out: bool,
}

impl Session {
    /// A region re-solve (sessions without an engine, see `incremental`), with the gauge
    /// anchors of the last full solve held fixed.
    #[allow(clippy::too_many_arguments)]
    fn resolve_regions(
        &self,
        problem: &mut Problem,
        index: &mut IncrementalSolver,
        seeds: &[usize],
        total: f64,
        debt: &mut f64,
        options: &SolverOptions,
        gauge: &[Key],
        on_iteration: &mut dyn FnMut(&solver::IterationReport) -> ControlFlow<()>,
        budget: &dyn solver::Budget,
    ) -> Result<incremental::Resolved, solver::SolverError> {
        // Held fixed: what the client fixed, and the gauge anchors of the last full solve (a
        // region never reaches a component without one: it would be singular and the re-solve
        // falls back to the whole problem).
        let anchors = incremental::held_fixed(problem, gauge);
        incremental::resolve(
            problem,
            index,
            seeds,
            &anchors,
            total,
            debt,
            options,
            on_iteration,
            budget,
        )
    }

    /// Returns the problem taken out for a solve (or a factorisation) and applies the batches
    /// that were queued meanwhile.
    pub(super) fn hand_back(&self, st: &mut State, problem: Problem, index: IncrementalSolver) {
        st.model.put_back(problem, index);
        // A deleted session's queued batches would only cost CPU for nobody.
        if st.schedule.phase.is_deleted() {
            st.schedule.drop_queued();
        }
        while let Some((seq, prepared, ids)) = st.schedule.next_queued() {
            self.apply_prepared(st, seq, prepared, ids);
        }
    }
}

/// A finished solve in the metrics and the log.
fn report_finished(result: &Result<incremental::Resolved, solver::SolverError>, start: Instant) {
    match result {
        Ok(r) => {
            crate::runtime::metrics::observe_solve(start.elapsed(), r.summary.iterations);
            tracing::debug!(
                chi2 = r.summary.final_chi2,
                iterations = r.summary.iterations,
                seconds = start.elapsed().as_secs_f64(),
                "solve finished"
            );
        }
        Err(e) => tracing::warn!("solve failed: {e}"),
    }
}
