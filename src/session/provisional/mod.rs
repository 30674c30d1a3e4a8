//! Bounded update latency (`max_update_ms`): provisional answers on the request path, the exact
//! solve off it.
//!
//! The exact incremental solve of an update is fast near the robot and slow when a loop
//! closure into an old part of a large map makes it refactor the top of the elimination tree
//! (hundreds of milliseconds at 100 000 poses); no exact solve avoids that (the map's tail
//! latency grows with it). A session with a budget therefore splits the answer, like GTSAM's
//! concurrent filter and smoother (Williams et al. 2013):
//! - the exact solve runs as before, on a pool worker, and takes in what arrived meanwhile
//!   when it is done;
//! - an update it has not reflected as soon as exact solves usually do (where that is within a
//!   tenth of the budget; else at once, as when the update arrived behind a running solve, see
//!   [`Latency::wait`]) is answered provisionally (`answer`): the recent
//!   variables ([`window`]) are re-solved against the rest of the map as clients last saw it,
//!   held fixed, and published at once;
//! - when the exact solve lands, everything it changed of what clients were given is published
//!   (the correction), its size measured and reported (`landing`), and the newer variables are
//!   answered again against it.
//!
//! Idle, the exact solve and its polish end at the batch optimum as without a budget.

mod answer;
mod landing;
mod window;

use std::collections::{HashMap, VecDeque};
use std::time::Duration;

use super::Session;
use crate::api::ServiceError;

use crate::api::latency::{Correction, CorrectionStats, LatencyReport, CORRECTIONS_KEPT};
use crate::problem::Key;
use crate::session::prepared::PreparedBatch;
pub(super) use landing::LandingRefresh;
pub(crate) use window::RecentWindow;

/// A session's budget and what its provisional answers left for the exact solve to correct.
#[derive(Debug)]
pub(crate) struct Latency {
    pub max_update_ms: u64,
    pub window: RecentWindow,
    /// The highest sequence a provisional answer covers.
    pub answered: u64,
    /// Variables holding a provisional value, with the sequence of the answer that gave it:
    /// the exact solve that covers them publishes its own value for each, moved or not.
    provisional: HashMap<Key, u64>,
    answers: u64,
    /// A batch with removals, fixes or guesses (the newest such sequence): the window does
    /// not know what it changed, so no provisional answer until the exact estimate covers it.
    structural: u64,
    /// The most recent corrections (the last is the last one), and how many there were.
    corrections: VecDeque<Correction>,
    correction_count: u64,
    /// How long the last exact solves took, and twice their median (see [`Latency::wait`]),
    /// computed as each solve lands rather than for every batch.
    solves: VecDeque<Duration>,
    usual_wait: Option<Duration>,
}

/// Appends `item`, dropping the oldest beyond `keep`.
fn push_bounded<T>(queue: &mut VecDeque<T>, keep: usize, item: T) {
    if queue.len() == keep {
        queue.pop_front();
    }
    queue.push_back(item);
}

/// One provisional answer of a session at a time (see `Session::answer_in_flight`): the
/// newest sequence asked for meanwhile, and whether an exact solve landed under it.
#[derive(Debug, Default)]
pub(crate) struct Flight {
    answering: std::sync::Mutex<()>,
    wanted: std::sync::atomic::AtomicU64,
    again: std::sync::atomic::AtomicBool,
}

/// Exact solves [`Latency::wait`] looks back on.
const SOLVES_KEPT: usize = 64;
/// The shortest wait for an exact solve (below it, answering provisionally costs about as much
/// as waiting).
const MIN_WAIT: Duration = Duration::from_micros(500);

impl Latency {
    pub fn new(max_update_ms: u64) -> Self {
        Self {
            max_update_ms,
            window: RecentWindow::default(),
            answered: 0,
            provisional: HashMap::new(),
            answers: 0,
            structural: 0,
            corrections: VecDeque::new(),
            correction_count: 0,
            solves: VecDeque::with_capacity(SOLVES_KEPT),
            usual_wait: None,
        }
    }

    /// How long an accepted batch waits for the exact solve before it is answered
    /// provisionally: as long as exact solves usually take (twice the median of the last
    /// [`SOLVES_KEPT`]) where that is within a tenth of the budget (the rest is for the
    /// provisional solve, the journal and the transport). Where exact solves usually take longer
    /// (a large map), waiting would mostly end in a provisional answer anyway, later: the batch
    /// waits only the shortest wait, for the exact solves that are still quick. The bound was a
    /// quarter, and the answer waited it in full: at 100 000 poses most answers waited 5 ms
    /// of a 20 ms budget, the p99 ×2.9 that of 10 000 poses, where exact solves are quick;
    /// with "usually" within the quarter it was still ×2.7 (exact solves of ~2 ms waited 4).
    /// Not at all when it arrived `behind` a running solve, which has to finish before its
    /// exact turn comes.
    pub fn wait(&self, behind: bool) -> Duration {
        let tenth = Duration::from_micros(self.max_update_ms * 100);
        if behind {
            return Duration::ZERO;
        }
        let usual = match self.usual_wait {
            Some(usual) if usual <= tenth => usual,
            Some(_) => MIN_WAIT,
            None => tenth,
        };
        // Never beyond the tenth, even when it is below the shortest wait (a 1 ms budget).
        usual.max(MIN_WAIT).min(tenth)
    }

    /// An exact solve took `took`.
    pub fn solved_in(&mut self, took: Duration) {
        push_bounded(&mut self.solves, SOLVES_KEPT, took);
        if self.solves.len() >= SOLVES_KEPT / 2 {
            let mut recent: Vec<Duration> = self.solves.iter().copied().collect();
            let mid = recent.len() / 2;
            let (_, median, _) = recent.select_nth_unstable(mid);
            self.usual_wait = Some(*median * 2);
        }
    }

    /// Takes in an accepted batch: its new variables and factors join the window (its factors
    /// then reach the problem shared with it); one that changes more than it adds stops
    /// provisional answers until the exact estimate covers it.
    pub fn take_in(&mut self, sequence: u64, prepared: &PreparedBatch) {
        if prepared.changes_more_than_it_adds() {
            self.structural = self.structural.max(sequence);
        }
        let keys = prepared.variables.iter().map(|v| v.key);
        self.window.record(sequence, keys, &prepared.factors);
    }

    pub fn report(&self, exact: u64) -> LatencyReport {
        let kept: Vec<Correction> = self.corrections.iter().copied().collect();
        LatencyReport {
            max_update_ms: self.max_update_ms,
            answered_sequence: self.answered.max(exact),
            exact_sequence: exact,
            provisional_answers: self.answers,
            last_correction: self.corrections.back().copied(),
            corrections: CorrectionStats::of(&kept, self.correction_count),
        }
    }

    fn record_correction(&mut self, correction: Correction) {
        push_bounded(&mut self.corrections, CORRECTIONS_KEPT, correction);
        self.correction_count += 1;
    }
}

impl Session {
    /// Gives a new session a latency budget (`max_update_ms`); graph kinds with the
    /// incremental engine only.
    pub fn set_latency_budget(&self, max_update_ms: u64) -> Result<(), ServiceError> {
        crate::api::latency::check_budget(max_update_ms)
            .map_err(|m| ServiceError::bad_request("invalid_value", "max_update_ms", m))?;
        if !self.kind.eliminate.is_empty()
            || self.kind.name == crate::api::catalogue::SLIDING_WINDOW
        {
            return Err(ServiceError::bad_request(
                "invalid_value",
                "max_update_ms",
                format!(
                    "a latency budget is for pose graph sessions (their incremental engine); `{}` sessions solve otherwise",
                    self.kind.name
                ),
            ));
        }
        if self.max_update_ms.set(max_update_ms).is_ok() {
            self.lock().latency = Some(Latency::new(max_update_ms));
        }
        Ok(())
    }

    pub fn max_update_ms(&self) -> Option<u64> {
        self.max_update_ms.get().copied()
    }

    /// Waits until the estimate reflects `sequence`, exactly or (with a budget) provisionally,
    /// at most `timeout`.
    pub async fn wait_answered(&self, sequence: u64, timeout: Duration) -> bool {
        let mut solved = self.solved.subscribe();
        let mut answered = self.answered.subscribe();
        let either = async {
            tokio::select! {
                r = solved.wait_for(|s| *s >= sequence) => r.is_ok(),
                r = answered.wait_for(|s| *s >= sequence) => r.is_ok(),
            }
        };
        tokio::time::timeout(timeout, either).await.unwrap_or(false)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_batch_waits_as_long_as_exact_solves_usually_take_where_that_fits_a_tenth_of_the_budget() {
        let mut latency = Latency::new(20);
        let ms = Duration::from_millis;
        // Too few solves seen: a tenth of the budget.
        assert_eq!(latency.wait(false), ms(2));
        assert_eq!(latency.wait(true), Duration::ZERO);
        for i in 0..SOLVES_KEPT {
            // Mostly 0.6 ms, now and then a long one: the median ignores them.
            let took = if i % 10 == 0 {
                ms(400)
            } else {
                Duration::from_micros(600)
            };
            latency.solved_in(took);
        }
        assert_eq!(latency.wait(false), Duration::from_micros(1200));
        for _ in 0..SOLVES_KEPT {
            latency.solved_in(Duration::from_micros(900));
        }
        assert_eq!(
            latency.wait(false),
            Duration::from_micros(1800),
            "within the tenth"
        );
        for _ in 0..SOLVES_KEPT {
            latency.solved_in(ms(30));
        }
        assert_eq!(
            latency.wait(false),
            MIN_WAIT,
            "exact solves usually too slow for the tenth: the shortest wait"
        );
        for _ in 0..SOLVES_KEPT {
            latency.solved_in(Duration::from_micros(50));
        }
        assert_eq!(latency.wait(false), MIN_WAIT);
        // A budget of 1 ms: a tenth of it, below the shortest wait otherwise taken.
        let mut tight = Latency::new(1);
        for _ in 0..SOLVES_KEPT {
            tight.solved_in(Duration::from_micros(50));
        }
        assert_eq!(tight.wait(false), Duration::from_micros(100));
    }
}
