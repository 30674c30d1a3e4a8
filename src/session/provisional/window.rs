//! The recent part of a session's map, kept beside the problem for provisional answers: the
//! variables the newest batches created (in creation order) and the factors those batches
//! added, shared with the problem (a factor is held by an `Arc`) so that they stay readable while
//! a worker has the problem.

use std::collections::VecDeque;
use std::sync::Arc;

use crate::factors::{Factor, RobustKernel, SqrtInformation};
use crate::problem::Key;
use crate::session::prepared::PreparedFactor;

/// Variables created before the exact estimate's sequence that a provisional answer still
/// moves: the stretch of trajectory a loop closure into the old map bends near the robot.
pub(super) const MARGIN_VARIABLES: usize = 48;
/// At most this many variables move in one provisional answer (the newest): what keeps its
/// cost bounded when the exact solve falls far behind.
pub(super) const MAX_FREE_VARIABLES: usize = 384;
/// The window never holds more than this many variables (and their batches' factors): an exact
/// solve far behind leaves older pending variables at their last provisional value.
const MAX_WINDOW_VARIABLES: usize = 4 * MAX_FREE_VARIABLES;

#[derive(Clone, Debug)]
pub(crate) struct WindowFactor {
    /// The batch that added it.
    pub sequence: u64,
    pub factor: Arc<dyn Factor>,
    pub sqrt_information: SqrtInformation,
    pub robust: Option<RobustKernel>,
}

#[derive(Debug, Default)]
pub(crate) struct RecentWindow {
    /// (sequence of the batch that created it, key), oldest first.
    variables: VecDeque<(u64, Key)>,
    factors: VecDeque<WindowFactor>,
}

impl RecentWindow {
    /// Records an accepted batch: its new variables and the factors that enter the problem
    /// (candidates held out of it are left out here too), sharing each factor with the problem.
    pub fn record(
        &mut self,
        sequence: u64,
        new_keys: impl IntoIterator<Item = Key>,
        factors: &[PreparedFactor],
    ) {
        self.variables
            .extend(new_keys.into_iter().map(|key| (sequence, key)));
        for f in factors.iter().filter(|f| !f.candidate) {
            self.factors.push_back(WindowFactor {
                sequence,
                factor: Arc::clone(&f.factor),
                sqrt_information: f.sqrt_information.clone(),
                robust: f.robust,
            });
        }
        self.trim_to(MAX_WINDOW_VARIABLES);
    }

    /// Forgets what the exact estimate covers (through `exact`), keeping the
    /// [`MARGIN_VARIABLES`] newest variables before it and the factors of their batches.
    pub fn settle(&mut self, exact: u64) {
        let newer = self
            .variables
            .iter()
            .rev()
            .take_while(|(s, _)| *s > exact)
            .count();
        self.trim_to(newer + MARGIN_VARIABLES);
    }

    fn trim_to(&mut self, keep: usize) {
        let drop = self.variables.len().saturating_sub(keep);
        self.variables.drain(..drop);
        let oldest = self.variables.front().map_or(u64::MAX, |&(s, _)| s);
        while self.factors.front().is_some_and(|f| f.sequence < oldest) {
            self.factors.pop_front();
        }
    }

    /// The variables that move in a provisional answer: those created after `exact` and the
    /// [`MARGIN_VARIABLES`] before them, at most the [`MAX_FREE_VARIABLES`] newest, oldest
    /// first, each with its batch's sequence.
    pub fn free(&self, exact: u64) -> Vec<(u64, Key)> {
        let newer = self
            .variables
            .iter()
            .rev()
            .take_while(|(s, _)| *s > exact)
            .count();
        let take = (newer + MARGIN_VARIABLES).min(MAX_FREE_VARIABLES);
        let skip = self.variables.len().saturating_sub(take);
        self.variables.iter().skip(skip).copied().collect()
    }

    /// The factors that touch a variable `moves` says is free.
    pub fn touching(&self, moves: impl Fn(Key) -> bool) -> Vec<WindowFactor> {
        self.factors
            .iter()
            .filter(|f| f.factor.keys().iter().any(|&k| moves(k)))
            .cloned()
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::between_se2::BetweenSe2;
    use crate::geometry::Se2;

    fn odometry(from: Key) -> PreparedFactor {
        PreparedFactor {
            factor: Arc::new(BetweenSe2::new(from, from + 1, Se2::new(1.0, 0.0, 0.0))),
            sqrt_information: SqrtInformation::identity(3),
            robust: None,
            candidate: false,
        }
    }

    #[test]
    fn settling_keeps_a_margin_before_the_exact_estimate() {
        let mut window = RecentWindow::default();
        for pose in 1..=200u64 {
            let factors = vec![odometry(pose - 1)];
            window.record(pose, [pose], &factors);
            // The window shares the problem's factor.
            assert_eq!(Arc::strong_count(&factors[0].factor), 2);
        }
        window.settle(150);
        let free = window.free(150);
        assert_eq!(free.len(), 50 + MARGIN_VARIABLES);
        assert_eq!(
            free.first(),
            Some(&(151 - MARGIN_VARIABLES as u64, 151 - MARGIN_VARIABLES as u64))
        );
        assert_eq!(free.last(), Some(&(200, 200)));
        // Every factor of a kept batch is kept, and only those.
        let kept = window.touching(|_| true);
        assert_eq!(kept.len(), free.len());
        assert!(window.touching(|k| k == 10).is_empty());
    }

    #[test]
    fn free_variables_are_bounded_when_the_exact_estimate_lags() {
        let mut window = RecentWindow::default();
        for pose in 1..=5000u64 {
            window.record(pose, [pose], &[odometry(pose - 1)]);
        }
        let free = window.free(0);
        assert_eq!(free.len(), MAX_FREE_VARIABLES);
        assert_eq!(free.last(), Some(&(5000, 5000)));
        assert!(window.touching(|_| true).len() <= MAX_WINDOW_VARIABLES);
    }

    #[test]
    fn candidates_stay_out_of_the_window() {
        let mut window = RecentWindow::default();
        let factors = vec![
            odometry(0),
            PreparedFactor {
                candidate: true,
                ..odometry(5)
            },
        ];
        window.record(1, [1], &factors);
        assert_eq!(window.touching(|_| true).len(), 1);
        assert_eq!(Arc::strong_count(&factors[1].factor), 1, "not shared");
    }
}
