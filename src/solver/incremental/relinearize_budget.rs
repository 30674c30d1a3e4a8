//! A polish step's budget: which of the variables past the relinearisation threshold one
//! update relinearises when what it may refactor is bounded (`UpdateParams::relinearize_scalars`).

use super::IncrementalEngine;
use crate::problem::Problem;

impl IncrementalEngine {
    /// Keeps of `moved` (variable, step) the largest steps whose refactoring fits in `budget`
    /// scalar columns (the first always), in that order: it stops at the first that does not
    /// fit. Relinearising v refactors the paths to the root of the elimination tree from v and
    /// from every variable its factors touch. What this costs is bounded by the budget too (a
    /// path walk stops where it overflows), not by how many variables moved: after a long
    /// stream that is nearly all of them.
    pub(super) fn within_budget(
        &mut self,
        problem: &Problem,
        moved: &mut Vec<(usize, f64)>,
        budget: usize,
    ) {
        moved.sort_unstable_by(|a, b| b.1.total_cmp(&a.1));
        let entries = problem.factors();
        let (mut marked, mut fresh) = (Vec::new(), Vec::new());
        let mut marked_scalars = 0;
        let mut kept = 0;
        'candidates: for &(v, _) in moved.iter() {
            fresh.clear();
            let mut fresh_scalars = 0;
            let touched = self.by_variable[v]
                .iter()
                .flat_map(|&f| entries[f as usize].variables());
            for &start in std::iter::once(&v).chain(touched) {
                let mut u = Some(start).filter(|&u| self.free[u]);
                while let Some(c) = u.filter(|&c| !self.mark[c]) {
                    self.mark[c] = true;
                    fresh.push(c);
                    fresh_scalars += self.dims[c];
                    if kept > 0 && marked_scalars + fresh_scalars > budget {
                        for &c in &fresh {
                            self.mark[c] = false;
                        }
                        break 'candidates;
                    }
                    u = self.factor.parent(c);
                }
            }
            marked.extend_from_slice(&fresh);
            marked_scalars += fresh_scalars;
            kept += 1;
        }
        moved.truncate(kept);
        for c in marked {
            self.mark[c] = false;
        }
    }
}
