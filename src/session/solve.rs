//! A session's solve on a pool worker: take the problem out of the state, re-solve it (as far as
//! the updates reach, see `incremental`), hand it back, apply what arrived meanwhile, publish the
//! estimate changes and the Summary, and reschedule if needed.

use std::ops::ControlFlow;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Instant;

use super::incremental::{self, IncrementalSolver};
use super::mirror;
use super::solve_budget::SolveBudget;
use super::Session;
use crate::api::wire::{Estimate, SessionEvent};
use crate::api::ErrorKind;
use crate::api::ServiceError;
use crate::problem::{Key, Problem};
use crate::runtime::pool::TIME_SLICE;
use crate::solver::{self, Budget as _, SolverOptions};

/// How long a session must be idle before it polishes its estimate.
const POLISH_AFTER_IDLE: std::time::Duration = std::time::Duration::from_millis(20);

/// What a solve takes out of the session state (the problem moves to the worker).
struct SolveWork {
    problem: Problem,
    index: IncrementalSolver,
    options: SolverOptions,
    sequence: u64,
    solve_number: u64,
    seeds: Vec<usize>,
    structural: bool,
    chi2: Option<f64>,
    debt: f64,
    gauge: Vec<Key>,
    /// A solve the client asked for, or a polish: an engine update runs to convergence.
    tight: bool,
}

impl Session {
    /// Takes the problem and what the next solve needs out of the state, or `None` when
    /// there is nothing to do.
    fn take_work(&self) -> Option<SolveWork> {
        let mut st = self.lock();
        if st.deleted || !st.dirty {
            st.scheduled = false;
            return None;
        }
        st.solving = true;
        st.dirty = false;
        // Tight (to convergence): a polish, or a solve the client asked for with nothing new
        // (or under the manual policy, where no polish follows). New factors otherwise take
        // the request-path thresholds and a polish follows.
        let forced = std::mem::replace(&mut st.forced, false);
        let tight = forced
            && (st.seeds.is_empty()
                || matches!(st.auto, crate::api::wire::AutoOptimize::Manual {}));
        st.factors_since_solve = 0;
        st.solves += 1;
        self.cancel.store(false, Ordering::SeqCst);
        Some(SolveWork {
            problem: st.problem.take().expect("one solve per session at a time"),
            index: st.index.take().expect("kept with the problem"),
            options: st.options.clone(),
            // Batches are applied as they come while the problem is here: it reflects them all.
            sequence: st.sequence,
            solve_number: st.solves,
            seeds: std::mem::take(&mut st.seeds),
            structural: std::mem::replace(&mut st.structural, false),
            chi2: st.chi2,
            debt: st.region_debt,
            gauge: st.gauge.clone(),
            tight,
        })
    }

    /// One solve on a pool worker: take the problem, optimise without the lock, hand it back,
    /// apply what arrived meanwhile, and reschedule if that needs another solve.
    pub(super) fn solve_once(self: Arc<Self>) {
        let Some(work) = self.take_work() else {
            return;
        };
        let SolveWork {
            mut problem,
            mut index,
            options,
            sequence,
            solve_number,
            seeds,
            structural,
            chi2,
            mut debt,
            gauge,
            tight,
        } = work;
        let _span =
            tracing::info_span!("session", session = %self.name, solve = solve_number).entered();
        let start = Instant::now();
        let mut preempted = false;
        let carried = self.lock().solve_carried;
        let budget = SolveBudget::new(&self, start, carried);
        let mut on_iteration = |report: &solver::IterationReport| {
            // Nothing is published of a batch before it is durable (see `journal_barrier`).
            self.journal_barrier();
            self.emit(SessionEvent::Iteration {
                session: self.name.clone(),
                solve: solve_number,
                sequence,
                report: report.clone(),
            });
            if budget.checkpoint().is_break() {
                return ControlFlow::Break(());
            }
            if self.pool.waiting() > 0 && start.elapsed() > TIME_SLICE {
                preempted = true;
                return ControlFlow::Break(());
            }
            ControlFlow::Continue(())
        };
        let solve = std::panic::AssertUnwindSafe(|| {
            let additions_only = !structural && solve_number > 1;
            if let Some(total) = chi2.filter(|_| additions_only) {
                match index.update_engine(
                    &mut problem,
                    total,
                    tight,
                    &options,
                    &gauge,
                    &mut on_iteration,
                ) {
                    Some(Ok(resolved)) => return Ok(resolved),
                    // The engine failed (an indeterminate update): solve in batch below.
                    Some(Err(e)) => {
                        tracing::debug!("incremental update failed, solving in batch: {e}")
                    }
                    // After additions only, re-solve as far as they reach.
                    None => {
                        return self.resolve_regions(
                            &mut problem,
                            &mut index,
                            &seeds,
                            total,
                            &mut debt,
                            &options,
                            &gauge,
                            &mut on_iteration,
                            &budget,
                        )
                    }
                }
            }
            // Later solves warm-start from the current estimate; initialisation is for the first.
            debt = 0.0;
            let solved = if solve_number > 1 {
                index.solve_whole(&mut problem, &options, &mut on_iteration, &budget)
            } else {
                solver::optimize_within(&mut problem, &options, &mut on_iteration, &budget)
            };
            let summary = solved?;
            if summary.converged {
                index.rebuild_engine(&mut problem, &summary.used.gauge_fixed);
            }
            Ok(incremental::Resolved {
                total_chi2: summary.final_chi2,
                converged: summary.converged,
                moved: None,
                summary,
            })
        });
        // A panic inside the solver is a bug; report it as a failed solve and keep the session.
        let result = std::panic::catch_unwind(solve)
            .unwrap_or_else(|_| Err(solver::SolverError::Internal("the solver panicked".into())));
        let timed_out = budget.timed_out();

        match &result {
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
        self.journal_barrier();
        let mut st = self.lock();
        st.solving = false;
        self.cancel.store(false, Ordering::SeqCst);
        let mut polish = false;
        match result {
            Ok(resolved) => {
                let summary = resolved.summary;
                if summary.used.region_variables.is_none() {
                    st.gauge = summary.used.gauge_fixed.clone();
                }
                st.chi2 = Some(resolved.total_chi2);
                st.converged = resolved.converged;
                st.last_error = None;
                // A preempted solve continues in its next turn (its time counts towards the
                // limit); a cancelled or timed-out one waits for news.
                if preempted && !timed_out {
                    st.dirty = true;
                    st.forced = true;
                    st.solve_carried = carried + start.elapsed();
                } else {
                    st.solve_carried = std::time::Duration::ZERO;
                }
                // An engine update that left steps above the threshold polishes once the
                // session is idle, unless the client decides when solves run: counted from
                // when this solve is published and handed back (below), so the time a large
                // update spends there does not count as idle.
                polish =
                    index.polish && !matches!(st.auto, crate::api::wire::AutoOptimize::Manual {});
                if timed_out {
                    st.converged = false;
                    st.last_error = Some(format!(
                        "the solve stopped at the time limit of {} ms (limits.max_solve_ms) after {} iterations; the estimate is the best it reached",
                        self.limits.max_solve_ms, summary.iterations
                    ));
                }
                let changed = mirror::refresh(
                    &mut st.mirror,
                    &problem,
                    resolved.moved.as_deref(),
                    sequence,
                );
                if !changed.is_empty() {
                    self.emit(SessionEvent::Estimate(Estimate {
                        session: self.name.clone(),
                        sequence,
                        variables: changed,
                    }));
                }
                self.emit(SessionEvent::Summary {
                    session: self.name.clone(),
                    solve: solve_number,
                    sequence,
                    summary: Box::new(summary.clone()),
                });
                st.last_summary = Some(summary);
            }
            Err(e) => {
                st.converged = false;
                // Whatever moved, the next solve starts from a clean slate.
                st.structural = true;
                // Stopped by the time limit before the first step: say which limit.
                let message = if timed_out {
                    format!(
                        "the solve stopped at the time limit of {} ms (limits.max_solve_ms): {e}",
                        self.limits.max_solve_ms
                    )
                } else {
                    e.to_string()
                };
                st.last_error = Some(message.clone());
                // Keep the last good values: the mirror is not refreshed from a failed solve.
                self.emit(SessionEvent::Error {
                    session: self.name.clone(),
                    sequence: Some(sequence),
                    error: ServiceError::new(ErrorKind::Invalid, "solve_failed", message).body,
                    producer: None,
                    producer_seq: None,
                });
            }
        }
        st.solved_sequence = st.solved_sequence.max(sequence);
        st.region_debt = debt;
        self.hand_back(&mut st, problem, index);
        if polish {
            self.polish_when_idle(st.sequence);
        }
        st.scheduled = false;
        self.solved.send_replace(st.solved_sequence);
        self.completed.send_modify(|n| *n = (*n).max(solve_number));
        self.maybe_schedule(&mut st);
    }
}

impl Session {
    /// Schedules a polish step (an engine update towards convergence, bounded in what it
    /// refactors) if no batch arrives within [`POLISH_AFTER_IDLE`]: a stream's next update
    /// never waits behind a polish, and a batch that arrives later waits for one step at most.
    fn polish_when_idle(self: &Arc<Self>, sequence: u64) {
        let session = Arc::clone(self);
        self.runtime.spawn(async move {
            tokio::time::sleep(POLISH_AFTER_IDLE).await;
            let mut st = session.lock();
            if st.sequence == sequence && !st.deleted && !st.solving && !st.scheduled {
                st.dirty = true;
                st.forced = true;
                session.schedule(&mut st);
            }
        });
    }

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
    pub(super) fn hand_back(
        &self,
        st: &mut super::State,
        problem: Problem,
        index: IncrementalSolver,
    ) {
        st.problem_bytes = super::state::problem_bytes(&problem) + index.engine_bytes();
        st.problem = Some(problem);
        st.index = Some(index);
        // A deleted session's queued batches would only cost CPU for nobody.
        if st.deleted {
            st.pending.clear();
            st.pending_factors = 0;
        }
        while let Some((seq, prepared, ids)) = st.pending.pop_front() {
            st.pending_factors -= prepared.factor_count();
            self.apply_prepared(st, seq, prepared, ids);
        }
    }
}
