//! A provisional answer: the recent variables re-solved against the rest of the map as clients
//! last saw it, off the session lock, and published as the estimate of the newest batch.
//!
//! The variables created after the exact estimate's sequence, and the stretch of trajectory
//! just before them (`window::MARGIN_VARIABLES`), move; every other variable their factors
//! reach (the old end of a loop closure, the pose before the stretch) is held at its published
//! value. A loop closure into the old map so bends the recent trajectory onto the map near the
//! robot at once; how it corrects distant poses waits for the exact solve. A variable no answer
//! has placed yet starts where its odometry from the placed ones predicts it (a client's guess
//! is in its own drifting frame).

use std::collections::{BTreeMap, HashSet};
use std::ops::ControlFlow;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::window::WindowFactor;
use crate::api::catalogue;
use crate::api::wire::{AutoOptimize, Estimate, SessionEvent};
use crate::problem::{Gauge, Key, Problem, Variable};
use crate::session::mirror::value_of;
use crate::session::{Session, State};
use crate::solver::{self, Initialization, Method, SolverOptions};

/// What a provisional answer solves, copied out of the state.
struct Work {
    /// The newest accepted sequence it answers, and the exact estimate's it starts from.
    through: u64,
    exact: u64,
    /// Every variable the factors reach, with its published value and whether it moves.
    variables: BTreeMap<Key, (Box<dyn Variable>, bool)>,
    /// Free variables no answer placed yet, in creation order.
    unplaced: Vec<Key>,
    factors: Vec<WindowFactor>,
}

impl Session {
    /// Answers `sequence` provisionally after `after`, unless the exact estimate (or another
    /// answer) reflects it by then; `again`: answer the newest batches again even if they were
    /// (an exact solve landed under them).
    pub(in crate::session) fn spawn_provisional_answer(
        self: &Arc<Self>,
        sequence: u64,
        after: Duration,
        again: bool,
    ) {
        let session = Arc::clone(self);
        let armed = Instant::now();
        // It waits for the journal and solves: off the async threads. The wait is the thread's
        // own sleep, not the runtime's timer, which rounds a deadline up to its next
        // millisecond tick: a wait of 2 ms took 2-3 ms plus a wake-up (stop 79).
        self.runtime.spawn_blocking(move || {
            if !after.is_zero() {
                std::thread::sleep(after);
            }
            if session.answer_in_flight(sequence, again) {
                crate::runtime::metrics::observe_provisional_answer(armed.elapsed());
            }
        });
    }

    /// Answers provisionally, one answer of the session at a time: a batch whose answer is due
    /// while another is being computed leaves its sequence to that one, which answers again
    /// when done (each answer covers every batch accepted before it). Producers that do not
    /// wait for answers so cost one provisional solve at a time, not one per batch in
    /// parallel. Whether an answer was published.
    fn answer_in_flight(self: &Arc<Self>, sequence: u64, again: bool) -> bool {
        let answered = *self.answered.borrow();
        // Answered already, or the session is going away (its waiters were released).
        if answered == u64::MAX || (answered >= sequence && !again) {
            return false;
        }
        let flight = &self.provisional_flight;
        flight.wanted.fetch_max(sequence, Ordering::SeqCst);
        if again {
            flight.again.store(true, Ordering::SeqCst);
        }
        let mut published = false;
        loop {
            // The one answering sees what this call asked for (checked after it lets go).
            let Ok(answering) = flight.answering.try_lock() else {
                return published;
            };
            loop {
                let wanted = flight.wanted.swap(0, Ordering::SeqCst);
                if wanted == 0 {
                    break;
                }
                let again = flight.again.swap(false, Ordering::SeqCst);
                published |= self.answer_provisionally(wanted, again);
            }
            drop(answering);
            if flight.wanted.load(Ordering::SeqCst) == 0 {
                return published;
            }
        }
    }

    /// Whether it published an answer.
    fn answer_provisionally(self: &Arc<Self>, sequence: u64, again: bool) -> bool {
        // An exact solve that lands while this one solves moves the values it held fixed: once
        // more against the new ones.
        for _ in 0..2 {
            let Some(work) = gather(&self.lock(), sequence, again) else {
                return false;
            };
            let (through, exact) = (work.through, work.exact);
            let Some(values) = work.solve() else {
                return false;
            };
            // Nothing of a batch is published before it is durable.
            self.journal_barrier();
            let mut st = self.lock();
            if st.results.solved_sequence == exact {
                self.publish_provisional(&mut st, through, values);
                return true;
            }
        }
        false
    }

    fn publish_provisional(
        &self,
        st: &mut State,
        through: u64,
        values: Vec<(Key, Box<dyn Variable>)>,
    ) {
        let State {
            mirror, latency, ..
        } = st;
        let Some(latency) = latency.as_mut() else {
            return;
        };
        let mut changed = Vec::new();
        let mut value = Vec::new();
        for (key, variable) in values {
            let Some(entry) = mirror.entries.get_mut(&key) else {
                continue;
            };
            // A client's guess newer than this answer stays.
            if entry.changed > through {
                continue;
            }
            catalogue::encode_variable_into(variable.as_ref(), &mut value);
            if entry.value[..] != value[..] {
                entry.value.clear();
                entry.value.extend_from_slice(&value);
                entry.changed = through;
                latency.provisional.insert(key, through);
                changed.push(value_of(key, entry));
            }
        }
        latency.answered = latency.answered.max(through);
        latency.answers += 1;
        // Even with nothing changed: the event tells subscribers the estimate reflects
        // `through` (as a summary does for an exact solve).
        self.emit(SessionEvent::Estimate(Estimate {
            session: self.name.clone(),
            sequence: through,
            variables: changed,
        }));
        self.answered.send_replace(latency.answered);
    }
}

/// Copies what the answer of `sequence` needs, or `None` when there is nothing to answer: the
/// exact estimate (or an answer, unless `again`) reflects it, a batch since the exact estimate
/// removed, fixed or moved something the window does not know of, or the session solves only
/// when its auto-optimise policy (not `every_batch`) says.
fn gather(st: &State, sequence: u64, again: bool) -> Option<Work> {
    let latency = st.latency.as_ref()?;
    let exact = st.results.solved_sequence;
    let through = st.mirror.sequence;
    let due = if again {
        through > exact
    } else {
        latency.unanswered(sequence, exact)
    };
    // Under another auto-optimise policy the client chose when the estimate changes.
    let every_batch = matches!(st.auto, AutoOptimize::EveryBatch {});
    if !due || latency.structural > exact || !every_batch {
        return None;
    }
    let free = latency.window.free(exact);
    let moving: HashSet<Key> = free.iter().map(|&(_, k)| k).collect();
    let factors = latency.window.touching(|k| moving.contains(&k));
    let mut variables = BTreeMap::new();
    for key in factors.iter().flat_map(|f| f.factor.keys()) {
        if variables.contains_key(key) {
            continue;
        }
        // A factor on a variable the mirror lacks (a robot's anchor) is left out below.
        if let Some(entry) = st.mirror.entries.get(key) {
            let moves = moving.contains(key) && !entry.fixed;
            variables.insert(*key, (entry.decode(), moves));
        }
    }
    let factors = factors
        .into_iter()
        .filter(|f| f.factor.keys().iter().all(|k| variables.contains_key(k)))
        .collect();
    let unplaced = free
        .iter()
        .filter(|&&(s, k)| s > exact && !latency.provisional.contains_key(&k))
        .map(|&(_, k)| k)
        .collect();
    Some(Work {
        through,
        exact,
        variables,
        unplaced,
        factors,
    })
}

impl Work {
    /// The moving variables' new values (`None` when the small solve failed: the answer
    /// waits for the exact one).
    fn solve(mut self) -> Option<Vec<(Key, Box<dyn Variable>)>> {
        self.place_by_odometry();
        let mut problem = Problem::with_gauge(Gauge::AnchorComponents);
        let mut moving = Vec::new();
        for (key, (value, moves)) in self.variables {
            problem.add_variable(key, value).ok()?;
            if moves {
                moving.push(key);
            } else {
                problem.set_fixed(key, true).ok()?;
            }
        }
        for f in self.factors {
            // A factor not finite at the published values gives the small solve nothing.
            let _ = problem.add_shared_factor_sqrt(
                f.factor,
                f.sqrt_information,
                f.robust,
                String::new(),
            );
        }
        let options = SolverOptions {
            method: Method::LevenbergMarquardt,
            // From the published values and odometry, a few steps reach what a provisional
            // answer needs; its cost stays bounded.
            max_iterations: 5,
            initialization: Initialization::None,
            ..SolverOptions::default()
        };
        solver::optimize(&mut problem, &options, &mut |_| ControlFlow::Continue(())).ok()?;
        Some(
            moving
                .into_iter()
                .filter_map(|k| Some((k, problem.values.get(k)?.clone_box())))
                .collect(),
        )
    }

    /// Starts every unplaced variable where a factor to placed ones predicts it (odometry
    /// from the previous pose), in creation order; one no factor predicts keeps its value.
    fn place_by_odometry(&mut self) {
        let mut unplaced: HashSet<Key> = self.unplaced.iter().copied().collect();
        for key in std::mem::take(&mut self.unplaced) {
            let predicted = self.factors.iter().find_map(|f| {
                let keys = f.factor.keys();
                let target = keys.iter().position(|&k| k == key)?;
                let known: Option<Vec<Option<&dyn Variable>>> = keys
                    .iter()
                    .enumerate()
                    .map(|(i, k)| match i == target {
                        true => Some(None),
                        false if unplaced.contains(k) => None,
                        false => self.variables.get(k).map(|(v, _)| Some(v.as_ref())),
                    })
                    .collect();
                f.factor.predict(&known?, target)
            });
            if let Some(value) = predicted.filter(|v| v.is_finite()) {
                if let Some(slot) = self.variables.get_mut(&key) {
                    slot.0 = value;
                }
            }
            unplaced.remove(&key);
        }
    }
}
