//! What a bundle adjustment session's solve does beyond a pose graph's.
//!
//! A bundle adjustment streamed camera by camera ends where its stream led it: each update
//! starts from the last estimate, and a map that few cameras constrain can carry points and
//! cameras into a minimum a batch solve from the same values never meets. Two things bring it
//! back:
//!
//! * **Lost points** (after every converged solve): a point behind every camera that sees it
//!   went through infinity, and no later update brings it back; it is triangulated again from
//!   its cameras (`solver::retriangulate`) and the whole problem solved once more.
//! * **A restart from the given values**: the session keeps the values its client gave (each
//!   variable's value and later guesses, [`GivenValues`]), and a solve the client asks for
//!   (`optimize`), or the one a stream's rest of 0.5 s brings (not under the `manual` policy),
//!   also solves the whole problem from them, as `factord ba` would, and keeps the lower of
//!   the two. The rest's restart gives way to the next batch. Once idle, the estimate is then
//!   at least as good as the batch solve of what was sent. (Pose graphs need neither: their
//!   polish reaches the batch optimum from the estimate.)
//!
//! Since the rest (or the client's `optimize`) takes the estimate to convergence, a streamed
//! update need not: it runs at most [`CAPPED_ITERATIONS`] iterations. An update whose new
//! camera disagrees with the map can otherwise crawl through a hundred Levenberg-Marquardt
//! steps of 10⁻⁴ each (problem-49 streamed camera by camera: 1.3-1.6 s per such update, against
//! 0.1-0.4 s at the cap). A solve a restart follows is capped too: the restart usually ends
//! lower than the crawl would, and only when it does not does the solve go on to convergence.

use std::ops::ControlFlow;

use super::incremental;
use super::solve::SolveWork;
use super::solve_budget::{SolveBudget, YieldToBatches};
use super::Session;
use crate::api::catalogue;
use crate::problem::{Key, Problem, Values};
use crate::solver::{self, IterationReport, SolverError};
use crate::variables::Variable;

/// The most iterations a bundle adjustment's solve runs (the session's `max_iterations` when
/// lower) when it need not converge: a streamed update (a solve after a batch, neither asked
/// for nor a rest's), or the solve before a restart from the given values. The first solve
/// runs to `max_iterations`.
pub(super) const CAPPED_ITERATIONS: usize = 20;

impl SolveWork {
    /// Caps this solve's iterations at [`CAPPED_ITERATIONS`] if it solves a bundle adjustment
    /// after the first and need not converge: a streamed update, or a solve a restart from the
    /// given values follows. [`SolveWork::uncap`] gives the session's limit back.
    pub(super) fn cap_bundle_iterations(&mut self) {
        if self.problem.eliminate.is_empty() || self.solve_number < 2 {
            return;
        }
        let streamed = !self.tight && !self.asked && !self.restart_when_idle;
        let restart_follows = (self.asked || self.restart_when_idle) && self.index.given.changed;
        if streamed || restart_follows {
            self.uncapped.get_or_insert(self.options.max_iterations);
            self.options.max_iterations = self.options.max_iterations.min(CAPPED_ITERATIONS);
        }
    }

    /// The session's `max_iterations` back; whether the solve was capped.
    fn uncap(&mut self) -> bool {
        match self.uncapped.take() {
            Some(iterations) => {
                self.options.max_iterations = iterations;
                true
            }
            None => false,
        }
    }
}

/// How a restart from the given values ended.
enum Restart {
    /// Lower than the estimate it started beside: it is the estimate now.
    Kept(incremental::Resolved),
    /// It ran its course and ended no lower: the estimate stays.
    NotLower(incremental::Resolved),
    /// Cut short (a batch arrived, another session's turn): the estimate stays.
    Interrupted(incremental::Resolved),
}

/// The values a bundle adjustment's client gave: the variables' values as they arrived, and
/// guesses since. Indexed like the problem's values; `None` where none was recorded. Snapshots
/// keep them (`journal::Snapshot::given`, tracked on the journal's side, since the problem is
/// out with a solve while a snapshot is written): a session restored from one restarts from
/// what its client sent, not from the estimate the snapshot holds.
#[derive(Debug, Default)]
pub(crate) struct GivenValues {
    values: Vec<Option<Box<dyn Variable>>>,
    /// Something was given since the last restart.
    changed: bool,
    /// Bytes the given values hold (see [`GivenValues::bytes`]).
    held: usize,
    /// Restored from a snapshot: the first solve starts from the snapshot's estimate, not from
    /// these, so it does not stand for a restart.
    restored: bool,
}

impl GivenValues {
    /// Records what the client gave for variable `index` of `problem` (its current value, just
    /// set from the batch). Only bundle adjustments keep them.
    pub fn record(&mut self, problem: &Problem, index: usize) {
        if problem.eliminate.is_empty() {
            return;
        }
        if self.values.len() < problem.values.len() {
            self.values.resize_with(problem.values.len(), || None);
        }
        self.replace(index, problem.values.variable(index).clone_box());
    }

    /// `value` as variable `index`'s given value (recorded before).
    fn replace(&mut self, index: usize, value: Box<dyn Variable>) {
        self.held += value_bytes(value.as_ref());
        if let Some(old) = self.values[index].replace(value) {
            self.held -= value_bytes(old.as_ref());
        }
        self.changed = true;
    }

    /// Bytes held (an estimate from sizes, as the problem's own accounting).
    pub fn bytes(&self) -> usize {
        self.values.len() * std::mem::size_of::<Option<Box<dyn Variable>>>() + self.held
    }

    /// Something was given since the last restart.
    pub fn changed(&self) -> bool {
        self.changed
    }

    /// No restart is due until something is given again.
    pub fn settle(&mut self) {
        self.changed = false;
    }

    /// `values` with the given ones in place.
    fn applied_to(&self, values: &Values) -> Values {
        let mut start = values.clone();
        for (index, given) in self.values.iter().enumerate() {
            if let Some(given) = given {
                start.set(index, given.as_ref());
            }
        }
        start
    }
}

/// A boxed value's heap bytes, estimated from its tangent (a camera: a quaternion, a
/// translation and three intrinsics; a point: three numbers).
fn value_bytes(value: &dyn Variable) -> usize {
    16 + 8 * value.tangent_dim()
}

impl Session {
    /// A snapshot's given values in place of its estimate, which restoring its variables
    /// recorded as given; tracked again for the next snapshot.
    pub(super) fn restore_given(&self, given: Vec<(Key, Vec<f64>)>) -> Result<(), String> {
        if given.is_empty() {
            return Ok(());
        }
        let mut st = self.lock();
        let mut durable = self.durable.lock().unwrap_or_else(|p| p.into_inner());
        let model = &mut st.model;
        let (Some(problem), Some(index)) = (model.problem.as_ref(), model.index.as_mut()) else {
            // Recovery solves nothing before it ends, so the problem is here.
            return Err("snapshot: the problem was out with a solve during recovery".into());
        };
        for (key, value) in given {
            let at = problem.values.index_of(key).ok_or_else(|| {
                format!("snapshot: a given value for variable {key}, which it does not hold")
            })?;
            let kind = problem.values.variable(at).kind();
            let codec = catalogue::variable_codec(kind).expect("every kind has a codec");
            let decoded = (codec.decode)(&value)
                .map_err(|e| format!("snapshot: the given value of variable {key}: {e}"))?;
            index.given.replace(at, decoded);
            index.given.restored = true;
            if let Some(d) = durable.as_mut() {
                d.track_given(key, value);
            }
        }
        Ok(())
    }

    /// A bundle adjustment's steps after its solve: lost points placed again, and a restart
    /// from the given values when the client asked for the solve or the session rested. Other
    /// problems, and solves that were interrupted, pass through; a solve that ran its course
    /// without converging (its iterations spent on a crawl) still restarts when asked or at
    /// rest, so an `optimize` that crawls ends at the batch solve all the same.
    pub(super) fn after_bundle_solve(
        &self,
        work: &mut SolveWork,
        resolved: incremental::Resolved,
        on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
        budget: &SolveBudget,
    ) -> Result<incremental::Resolved, SolverError> {
        let interrupted =
            resolved.summary.termination.reason == solver::TerminationReason::Interrupted;
        if work.problem.eliminate.is_empty() || interrupted {
            return Ok(resolved);
        }
        if work.solve_number == 1 && !work.index.given.restored {
            // The first solve started from the given values: a restart would repeat it.
            work.index.given.settle();
        }
        let resolved = self.place_lost_points(work, resolved, on_iteration, budget)?;
        let asked_or_rested = work.asked || work.restart_when_idle;
        let resolved = if asked_or_rested && work.index.given.changed {
            let cut_short = work.uncap() && !resolved.converged;
            // Asked for, the client waits for the restart; at rest, it gives way to the stream.
            let yielding = YieldToBatches {
                budget,
                sequence: work.sequence,
            };
            let restart_budget: &dyn solver::Budget = if work.asked { budget } else { &yielding };
            let restarted = self.restart_from_given(work, resolved, on_iteration, restart_budget);
            if budget.timed_out() {
                // Past `max_solve_ms`: it would be again, at every rest.
                work.index.given.settle();
            }
            match restarted? {
                // The solve before the restart stopped at its cap: it goes on to convergence.
                Restart::NotLower(_) if cut_short => {
                    let index = &mut work.index;
                    let problem = &mut work.problem;
                    let summary =
                        index.solve_whole(problem, &work.options, on_iteration, restart_budget)?;
                    let resolved = index.adopt_whole(problem, summary);
                    self.place_lost_points(work, resolved, on_iteration, restart_budget)?
                }
                Restart::Kept(resolved)
                | Restart::NotLower(resolved)
                | Restart::Interrupted(resolved) => resolved,
            }
        } else {
            resolved
        };
        if resolved.moved.is_none() {
            work.debt = 0.0;
        }
        Ok(resolved)
    }

    /// Points a converged solve left behind every camera that sees them, triangulated again,
    /// and the whole problem solved once more from there. A solve that did not converge passes
    /// through: mid-way (stopped by its iteration cap) a point behind its cameras may be on its
    /// way back, and placing it then left problem-49's stream at 18 × its cost.
    fn place_lost_points(
        &self,
        work: &mut SolveWork,
        resolved: incremental::Resolved,
        on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
        budget: &dyn solver::Budget,
    ) -> Result<incremental::Resolved, SolverError> {
        if !resolved.converged {
            return Ok(resolved);
        }
        let lost = solver::retriangulate::lost_points(&work.problem);
        let placed = solver::retriangulate::retriangulate(&mut work.problem, &lost);
        if placed.is_empty() {
            return Ok(resolved);
        }
        tracing::info!(
            session = %self.name,
            points = placed.len(),
            "points lost behind their cameras triangulated again"
        );
        let index = &mut work.index;
        let summary = index.solve_whole(&mut work.problem, &work.options, on_iteration, budget)?;
        Ok(index.adopt_whole(&mut work.problem, summary))
    }

    /// The whole problem solved again from the given values, kept if it ends lower than
    /// `resolved` (which it replaces); otherwise `resolved` as it is.
    fn restart_from_given(
        &self,
        work: &mut SolveWork,
        resolved: incremental::Resolved,
        on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
        budget: &dyn solver::Budget,
    ) -> Result<Restart, SolverError> {
        let SolveWork {
            problem,
            index,
            options,
            ..
        } = work;
        let start = index.given.applied_to(&problem.values);
        let streamed = std::mem::replace(&mut problem.values, start);
        let restarted = solver::optimize_within(problem, options, on_iteration, budget);
        let better =
            matches!(&restarted, Ok(s) if s.converged && s.final_chi2 < resolved.total_chi2);
        // A restart cut short (a batch arrived, another session's turn) runs again at the next
        // rest or ask; one that ran its course, converged or not, is not repeated.
        let interrupted = matches!(&restarted,
            Ok(s) if s.termination.reason == solver::TerminationReason::Interrupted);
        index.given.changed = interrupted;
        tracing::info!(
            session = %self.name,
            streamed = resolved.total_chi2,
            restarted = restarted.as_ref().map_or(f64::NAN, |s| s.final_chi2),
            kept = if better { "restarted" } else { "streamed" },
            "bundle adjustment restarted from the given values"
        );
        if !better {
            problem.values = streamed;
            return Ok(match interrupted {
                true => Restart::Interrupted(resolved),
                false => Restart::NotLower(resolved),
            });
        }
        let summary = restarted?;
        Ok(Restart::Kept(index.adopt_whole(problem, summary)))
    }
}
