//! A whole-map relinearisation computed beside a session's streamed updates.
//!
//! When a streamed update finds most of a large map past the relinearisation threshold (a loop
//! closure that corrects the whole map), relinearising it refactors nearly every column: on
//! M3500 7.3 ms of ordering, factorisation and solve, against ~0.5 ms for a usual update. The
//! session defers it (`incremental::DEFER_FROM_VARIABLES`), but only for so many updates: the
//! answers meanwhile solve the linear system at the older linearisation point and drift from
//! the optimum. Two robots streamed into M3500 kept the map under correction so long that
//! every 17th update relinearised it, and those were the stream's p99.
//!
//! So a deferring update (the eighth in a row, `incremental::START_BESIDE_AFTER`) starts the
//! relinearisation on another thread instead. That thread builds a new engine on a copy of
//! the problem (values copied, factors shared) at the estimate of that moment, as `SCHED_IDLE`:
//! on a core nothing else wants. At nice 10 it still slowed the zenoh path's threads (answers
//! over 3 ms doubled). Meanwhile the session's updates go on deferring with the old engine.
//! Each of them sends the thread what it appended to the problem (`Beside::send_appended`),
//! and the thread, once built, takes that in too, as updates of the new engine, until it has
//! caught up. The first update after it is done takes the new engine over, writes its estimate
//! of the whole map, and takes in what the thread had not caught up with as any update does
//! (an engine takes in what was appended to the problem since its last update). Taking in the
//! 10–40 poses that arrived while it built cost that update 1.8–3.5 ms on M3500 (ordering and
//! factorising them in the new engine), which made the take-overs the p99 of two robots.
//!
//! The copy costs the update that starts it 0.5–0.8 ms on M3500 (allocations: values, weights,
//! indices, labels); the old engine is freed on a thread of its own (0.6–1.3 ms). A batch
//! solve, a removal, a failed update or a polish that finds it still running drops it: its
//! thread finishes and its result is thrown away.

use std::sync::mpsc::{self, Receiver, Sender, TryRecvError};
use std::sync::Arc;

use crate::problem::{FactorEntry, Key, Problem};
use crate::solver::incremental::{IncrementalEngine, UpdateParams};
use crate::solver::SolverError;

/// A relinearisation running beside the session's updates.
#[derive(Debug)]
pub(crate) struct Beside {
    result: Receiver<Result<IncrementalEngine, SolverError>>,
    appended: Sender<Appended>,
    /// Variables and factors of the session's problem the thread has (its copy's sizes).
    sent_variables: usize,
    sent_factors: usize,
}

/// What the session appended to its problem after the thread's copy was made: variables (key,
/// estimate, held) and factors, in the problem's order.
struct Appended {
    variables: Vec<(Key, Box<dyn crate::variables::Variable>, bool)>,
    factors: Vec<FactorEntry>,
}

/// Rounds of catching up at most: each takes in what arrived during the one before, so this
/// bounds only a thread that never catches up (the session drops it after
/// `incremental::MAX_DEFERRED_BESIDE` updates anyway).
const MAX_CATCH_UP_ROUNDS: usize = 8;

/// How far a relinearisation beside the updates has come.
enum Progress {
    Running,
    Done(Box<IncrementalEngine>),
    /// It failed (an indeterminate system at that estimate) or its thread is gone: the
    /// session relinearises on its own path again.
    Failed,
}

impl Beside {
    /// Starts building an engine at `problem`'s current estimate, with the variables marked in
    /// `fixed` held; `None` when no thread could be started, or while a thread this session
    /// started earlier (`threads`, one reference held by each) still runs.
    ///
    /// It builds as `build` says, then takes in what [`Beside::send_appended`] sent meanwhile as
    /// `catch_up` says: a streamed update's, which defers a correction of the whole map. The
    /// map is still being corrected while it builds, and relinearising it whole again at each
    /// catch-up kept the thread from ever catching up (two robots into M3500: every 33rd
    /// update relinearised on its own path).
    pub fn start(
        problem: &Problem,
        fixed: Vec<bool>,
        (build, catch_up): (UpdateParams, UpdateParams),
        threads: &Arc<()>,
    ) -> Option<Self> {
        // A dropped relinearisation's thread finishes on its own, at the lowest priority: on a
        // machine without an idle core that can take long, and starting more beside it would
        // pile up copies of the problem.
        if Arc::strong_count(threads) > 1 {
            return None;
        }
        let mut copy = problem.clone();
        let (sender, result) = mpsc::sync_channel(1);
        let (appended, arrivals) = mpsc::channel();
        let running = Arc::clone(threads);
        std::thread::Builder::new()
            .name("factord-relinearize".into())
            .spawn(move || {
                let _running = running;
                super::background_priority::lower_for_good();
                let built = IncrementalEngine::new_with(&mut copy, &fixed, &build).and_then(
                    |mut engine| {
                        take_in_arrivals(&mut engine, &mut copy, &arrivals, &catch_up)?;
                        Ok(engine)
                    },
                );
                // The session may have dropped it meanwhile; then nobody wants the result.
                let _ = sender.send(built);
                // The copy is freed here, off the request path too.
            })
            .map_err(|e| tracing::debug!("no thread to relinearise beside the updates: {e}"))
            .ok()?;
        Some(Self {
            result,
            appended,
            sent_variables: problem.values.len(),
            sent_factors: problem.factors().len(),
        })
    }

    /// Sends the thread the variables and factors appended to `problem` since its copy or the
    /// last call (a few per streamed update: microseconds), to take in once it is built.
    pub fn send_appended(&mut self, problem: &Problem) {
        let (n, m) = (problem.values.len(), problem.factors().len());
        if n == self.sent_variables && m == self.sent_factors {
            return;
        }
        let values = &problem.values;
        let variables = (self.sent_variables..n)
            .map(|v| {
                (
                    values.key(v),
                    values.variable(v).clone_box(),
                    values.is_fixed(v),
                )
            })
            .collect();
        let factors = problem.factors()[self.sent_factors..].to_vec();
        (self.sent_variables, self.sent_factors) = (n, m);
        // A thread that is done no longer listens: the update taking over takes these in.
        let _ = self.appended.send(Appended { variables, factors });
    }

    fn progress(&self) -> Progress {
        match self.result.try_recv() {
            Ok(Ok(engine)) => Progress::Done(Box::new(engine)),
            Ok(Err(e)) => {
                tracing::debug!("the relinearisation beside the updates failed: {e}");
                Progress::Failed
            }
            Err(TryRecvError::Empty) => Progress::Running,
            Err(TryRecvError::Disconnected) => Progress::Failed,
        }
    }
}

/// Takes what the session appended while `engine` was built (and while it took that in) into
/// `copy` and `engine`, so that the update taking it over finds little left to do.
fn take_in_arrivals(
    engine: &mut IncrementalEngine,
    copy: &mut Problem,
    arrivals: &Receiver<Appended>,
    params: &UpdateParams,
) -> Result<(), SolverError> {
    for _ in 0..MAX_CATCH_UP_ROUNDS {
        let mut any = false;
        while let Ok(appended) = arrivals.try_recv() {
            appended.append_to(copy)?;
            any = true;
        }
        if !any {
            break;
        }
        engine.update(copy, params)?;
    }
    Ok(())
}

impl Appended {
    fn append_to(self, copy: &mut Problem) -> Result<(), SolverError> {
        for (key, variable, held) in self.variables {
            // The copy mirrors the session's problem, which took these keys: a failure here
            // is a bug, and the session then relinearises on its own path.
            let v = copy
                .add_variable(key, variable)
                .map_err(|e| SolverError::Internal(format!("the copy beside the updates: {e}")))?;
            copy.values.set_fixed(v, held);
        }
        for entry in self.factors {
            copy.push_entry(entry);
        }
        Ok(())
    }
}

/// Takes over the engine relinearised `beside` the updates when it is done, and gives the
/// problem its estimate; whether it did. A polish (`tight`) drops one still running: it
/// relinearises on its own, and idle time is what it has.
pub(crate) fn take_over(
    beside: &mut Option<Beside>,
    engine: &mut Option<IncrementalEngine>,
    problem: &mut Problem,
    tight: bool,
) -> bool {
    let Some(running) = beside else {
        return false;
    };
    match running.progress() {
        Progress::Done(built) => {
            built.write_estimate(problem);
            if let Some(old) = engine.replace(*built) {
                retire(old);
            }
            *beside = None;
            true
        }
        Progress::Running if !tight => false,
        Progress::Running | Progress::Failed => {
            *beside = None;
            false
        }
    }
}

/// Frees an engine that was taken over on a thread of its own: its factor and linearised
/// factors are thousands of allocations, whose freeing took 0.6–1.3 ms of the update that took
/// over on M3500.
fn retire(engine: IncrementalEngine) {
    // Where no thread can be started, the closure is dropped here, and the engine with it.
    let _ = std::thread::Builder::new()
        .name("factord-retire".into())
        .spawn(move || drop(engine));
}

#[cfg(test)]
mod tests {
    use std::ops::ControlFlow;
    use std::time::Duration;

    use nalgebra::DMatrix;

    use super::super::incremental::IncrementalSolver;
    use super::{Beside, Progress};
    use crate::factors::between_se2::BetweenSe2;
    use crate::geometry::Se2;
    use crate::problem::Problem;
    use crate::solver::incremental::UpdateParams;
    use crate::solver::{self, SolverOptions};
    use std::sync::Arc;

    fn odometry(problem: &mut Problem, from: u64) {
        let information = DMatrix::identity(3, 3) * 100.0;
        let z = Se2::new(1.0, 0.0, 0.0);
        let at = problem
            .values
            .variable(problem.values.index_of(from).unwrap());
        let at = *at.as_any().downcast_ref::<Se2>().unwrap();
        problem
            .add_variable(from + 1, Box::new(at.compose(&z)))
            .expect("a new pose");
        problem
            .add_factor(
                Box::new(BetweenSe2::new(from, from + 1, z)),
                &information,
                None,
                "odometry",
            )
            .expect("odometry");
    }

    /// `poses` 2D poses along x at their odometry, pose 0 held.
    fn chain(poses: u64) -> Problem {
        let mut problem = Problem::new();
        problem
            .add_variable(0, Box::new(Se2::new(0.0, 0.0, 0.0)))
            .unwrap();
        problem.set_fixed(0, true).unwrap();
        for pose in 0..poses - 1 {
            odometry(&mut problem, pose);
        }
        problem
    }

    /// A loop closure that bends a whole chain is relinearised beside the updates that follow,
    /// and the first update after it is done takes the new engine over; polished, the estimate
    /// is the batch optimum.
    #[test]
    fn a_whole_map_correction_is_relinearised_beside_and_taken_over() {
        let mut problem = chain(1500);
        let mut index = IncrementalSolver::default();
        index.extend(&problem, 0);
        index.rebuild_engine(&mut problem, &[]);
        // The closure says the chain is 99 m shorter and bent: every pose moves.
        let first = problem.factors().len();
        problem
            .add_factor(
                Box::new(BetweenSe2::new(0, 1499, Se2::new(1400.0, 30.0, 0.05))),
                &(DMatrix::identity(3, 3) * 100.0),
                None,
                "closure",
            )
            .unwrap();
        index.extend(&problem, first);
        let options = SolverOptions::default();
        let update = |problem: &mut Problem, index: &mut IncrementalSolver, tight: bool| {
            let total = problem.chi2();
            index
                .update_engine(problem, total, tight, &options, &[], &mut |_| {
                    ControlFlow::Continue(())
                })
                .expect("an engine")
                .expect("an update")
        };
        update(&mut problem, &mut index, false);
        let mut taken_over_at = None;
        for pose in 1499..1599 {
            let first = problem.factors().len();
            odometry(&mut problem, pose);
            index.extend(&problem, first);
            if update(&mut problem, &mut index, false).moved.is_none() {
                taken_over_at = Some(pose);
                break;
            }
            // Time for the thread beside, once it started (after 8 deferring updates).
            std::thread::sleep(Duration::from_millis(20));
        }
        let taken_over_at = taken_over_at.expect("the engine relinearised beside was taken over");
        assert!(
            taken_over_at < 1499 + 32,
            "taken over before the updates would relinearise on their own path ({taken_over_at})"
        );
        while !update(&mut problem, &mut index, true).converged {}
        let polished = problem.chi2();
        let mut batch = problem.clone();
        solver::optimize(&mut batch, &options, &mut |_| ControlFlow::Continue(())).unwrap();
        let optimum = batch.chi2();
        assert!(
            (polished - optimum).abs() <= 1e-6 * optimum,
            "polished {polished} against the batch optimum {optimum}"
        );
    }

    /// What the session appends while the thread builds is taken in by the thread, and the
    /// engine it hands over knows it, at the estimate a solve of the whole chain gives.
    #[test]
    fn what_arrives_while_it_builds_is_taken_in_beside() {
        let mut problem = chain(3000);
        let fixed: Vec<bool> = (0..problem.values.len())
            .map(|v| problem.values.is_fixed(v))
            .collect();
        let params = UpdateParams::default();
        let threads = Arc::new(());
        let mut beside =
            Beside::start(&problem, fixed, (params, params), &threads).expect("a thread");
        // Sent while the thread builds 3 000 poses (milliseconds, at the lowest priority).
        for pose in 2999..3009 {
            odometry(&mut problem, pose);
            // Off its odometry by 0.5 m: the catch-up solves it back onto the chain.
            let last = problem.values.len() - 1;
            problem.values.variable_mut(last).retract(&[0.5, 0.0, 0.0]);
        }
        beside.send_appended(&problem);
        let engine = loop {
            match beside.progress() {
                Progress::Done(engine) => break engine,
                Progress::Running => std::thread::sleep(Duration::from_millis(1)),
                Progress::Failed => panic!("the relinearisation beside failed"),
            }
        };
        assert_eq!(
            engine.variables(),
            3010,
            "the arrivals were taken in beside"
        );
        engine.write_estimate(&mut problem);
        let last = problem.values.get_as::<Se2>(3009).expect("pose 3009");
        assert!(
            (last.x - 3009.0).abs() < 1e-6 && last.y.abs() < 1e-6,
            "pose 3009 at {last:?}"
        );
    }

    /// A session starts no second relinearisation while the thread of one it dropped still
    /// runs; the thread's reference goes when it ends.
    #[test]
    fn one_thread_at_a_time() {
        let problem = chain(21);
        let fixed: Vec<bool> = (0..problem.values.len())
            .map(|v| problem.values.is_fixed(v))
            .collect();
        let params = UpdateParams::default();
        let threads = Arc::new(());
        let still_running = Arc::clone(&threads);
        assert!(Beside::start(&problem, fixed.clone(), (params, params), &threads).is_none());
        drop(still_running);
        let beside = Beside::start(&problem, fixed, (params, params), &threads).expect("a thread");
        while matches!(beside.progress(), Progress::Running) {
            std::thread::sleep(Duration::from_millis(1));
        }
        for _ in 0..1000 {
            if Arc::strong_count(&threads) == 1 {
                return;
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        panic!("the thread's reference outlived it");
    }
}
