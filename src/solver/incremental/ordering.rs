//! The elimination order of the part of the factor an update eliminates again.
//!
//! Its graph is what the affected variables share: the factors among them, and, for every
//! untouched column that reaches them, the clique of its affected rows (the fill that subtree
//! left on them, iSAM2's cached factors of orphaned subtrees). AMD orders that graph (or
//! METIS nested dissection, for a large part where that needs fewer flops), and the variables
//! of the update's new factors are then moved last (in that order otherwise): the constraint
//! of CCOLAMD that iSAM2 applies, so the newest poses become the root and the next update
//! (odometry from the newest pose) refactors a column or two, while a loop closure refactors
//! a path to the root, not the map.

use super::beside::run_beside;
use super::elimination_cost::elimination_flops;
use std::sync::{Mutex, PoisonError};

use crate::solver::structure::BlockOrdering;

/// Refactored parts of at least this many variables may be ordered by nested dissection
/// (METIS) instead of AMD; for smaller ones METIS seldom finds an order worth its time. On
/// the 10 000-pose city it was tried on 1 011 parts of 128–2 000 variables and kept on 95 (its
/// flops there a median 1.2 × AMD's), against 38 kept of 44 parts above 2 000 (its flops a
/// median 0.53–0.73 × AMD's). The generated 3D garage (5 000 poses) kept it on 16 of 320
/// tries, all below 500 variables, while each try cost its update 2–7 ms of ordering: from
/// 2 000 instead of 128, the two- and four-robot garage streams' waited p99 fell 15–19 % (HTTP
/// and zenoh), sphere2500's stream took 6 % less, and the 10 000-pose city and M3500 stayed
/// within their noise (`benches/history/issue-54-robots.md`, stop 77).
const NESTED_DISSECTION_FROM: usize = 2000;

/// Nested dissection is tried only where AMD's order needs more factorisation flops per
/// variable than this, and kept only where it needs fewer flops than AMD's. METIS costs about
/// 3 µs per variable (M3500's 2 500-variable parts: 7 ms), a few thousand flops of our
/// factorisation; above this its cost is a few percent of the refactor it may shrink, below
/// it the refactor is cheap anyway (the 2D acceptance files stay below 16k; sphere2500's 6-dim
/// parts are at 340k–700k).
/// Since the runs of a clique are factored as dense fronts, a flop costs less time, and the
/// trial pays from lower down: with 128 variables and 3e4 flops per variable (was 256 and 1e5)
/// the 10k stream's factorisation took 27–30 s instead of 41–43 s, for ~1 s more ordering.
/// (The size has since risen to [`NESTED_DISSECTION_FROM`]: most of that gain was the large
/// parts'.)
const NESTED_DISSECTION_ABOVE_FLOPS_PER_VARIABLE: f64 = 3e4;

/// `affected` in the order to eliminate them. `neighbours(v, out)` lists the affected
/// variables sharing a factor with `v`; `cliques` are groups of affected variables that fill
/// in together; `last[v]` marks the variables to eliminate last; `trials` remembers, per size
/// of part, whether METIS was worth trying (the next part that size starts it beside AMD).
pub fn order_affected(
    affected: &[usize],
    mut neighbours: impl FnMut(usize, &mut Vec<usize>),
    cliques: &[Vec<usize>],
    last: &[bool],
    dims: &[usize],
    local: &mut [u32],
    trials: &mut TrialHistory,
) -> Vec<usize> {
    for (i, &v) in affected.iter().enumerate() {
        local[v] = i as u32;
    }
    // Each list sized once: grown push by push, their reallocations were about 1 % of a 10k
    // stream (`perf`).
    let mut from_cliques = vec![0usize; affected.len()];
    for clique in cliques {
        for &a in clique {
            from_cliques[local[a] as usize] += clique.len() - 1;
        }
    }
    let mut out = Vec::new();
    let mut adjacency: Vec<Vec<usize>> = Vec::with_capacity(affected.len());
    for (&v, &extra) in affected.iter().zip(&from_cliques) {
        out.clear();
        neighbours(v, &mut out);
        let mut list = Vec::with_capacity(out.len() + extra);
        list.extend(out.iter().map(|&u| local[u] as usize));
        adjacency.push(list);
    }
    for clique in cliques {
        for &a in clique {
            for &b in clique {
                if a != b {
                    adjacency[local[a] as usize].push(local[b] as usize);
                }
            }
        }
    }
    // Local indices in elimination order, the constrained variables moved last.
    let constrained_last = |block_at: Vec<usize>| -> Vec<usize> {
        let (mut order, constrained): (Vec<usize>, Vec<usize>) =
            block_at.into_iter().partition(|&i| !last[affected[i]]);
        order.extend(constrained);
        order
    };
    let chosen = if affected.len() < NESTED_DISSECTION_FROM {
        constrained_last(BlockOrdering::amd_order(&adjacency))
    } else {
        let flops = |order: &[usize]| elimination_flops(&adjacency, order, |i| dims[affected[i]]);
        let by_amd = || {
            let order = constrained_last(BlockOrdering::amd_order(&adjacency));
            let flops = flops(&order);
            (order, flops)
        };
        let by_nd = || {
            let order = constrained_last(nested_dissection(&adjacency)?);
            let flops = flops(&order);
            Some((order, flops))
        };
        // Where the last part of this size needed the trial, METIS starts at once on a second
        // thread, beside AMD: the trial is decided on AMD's flops as before, so the order kept
        // is the same, only sooner (sphere2500 tries nearly every part).
        let ((by_amd, amd_flops), speculative) = if trials.expects_trial(affected.len()) {
            let (amd, nd) = run_beside(by_amd, by_nd);
            (amd, Some(nd))
        } else {
            (by_amd(), None)
        };
        let worth_trying =
            amd_flops >= NESTED_DISSECTION_ABOVE_FLOPS_PER_VARIABLE * affected.len() as f64;
        trials.record(affected.len(), worth_trying);
        let by_nd = if worth_trying {
            speculative.unwrap_or_else(by_nd)
        } else {
            None
        };
        match by_nd {
            Some((by_nd, nd_flops)) if nd_flops < amd_flops => by_nd,
            _ => by_amd,
        }
    };
    chosen.into_iter().map(|i| affected[i]).collect()
}

/// Per size class of refactored parts (powers of two of their variables), whether the last
/// part of that class was worth a nested-dissection trial: a stream's parts of one size are
/// alike (sphere2500's always are, the 2D files' small parts never), so the next one likely is.
#[derive(Debug, Default)]
pub struct TrialHistory {
    worth_trying: u64,
}

impl TrialHistory {
    fn class(variables: usize) -> u32 {
        (usize::BITS - variables.leading_zeros()).min(63)
    }

    fn expects_trial(&self, variables: usize) -> bool {
        self.worth_trying & (1 << Self::class(variables)) != 0
    }

    fn record(&mut self, variables: usize, worth_trying: bool) {
        let bit = 1 << Self::class(variables);
        if worth_trying {
            self.worth_trying |= bit;
        } else {
            self.worth_trying &= !bit;
        }
    }
}

/// Held while METIS runs. METIS seeds its random generator at every call, but the generator's
/// state is a static of the process (GKlib's `random.c`): sessions ordering at once raced on it
/// (a data race in C code, and orders that depended on what other sessions did meanwhile). One
/// call at a time, an order depends only on its graph; a session waits for at most the calls
/// already queued (METIS takes about 3 µs per variable).
static METIS: Mutex<()> = Mutex::new(());

/// METIS nested dissection of `adjacency`: the vertex at each position (`None` if METIS
/// fails).
fn nested_dissection(adjacency: &[Vec<usize>]) -> Option<Vec<usize>> {
    let n = adjacency.len();
    let mut xadj: Vec<metis_sys::idx_t> = Vec::with_capacity(n + 1);
    let mut adjncy: Vec<metis_sys::idx_t> = Vec::new();
    xadj.push(0);
    for (i, list) in adjacency.iter().enumerate() {
        let mut l: Vec<usize> = list.iter().copied().filter(|&j| j != i).collect();
        l.sort_unstable();
        l.dedup();
        adjncy.extend(l.iter().map(|&j| j as metis_sys::idx_t));
        xadj.push(adjncy.len() as metis_sys::idx_t);
    }
    let mut nv = n as metis_sys::idx_t;
    let mut perm = vec![0 as metis_sys::idx_t; n];
    let mut iperm = vec![0 as metis_sys::idx_t; n];
    // METIS keeps no Rust state, so a panic elsewhere while the lock was held left nothing to
    // repair: a poisoned lock is taken as it is.
    let _one_at_a_time = METIS.lock().unwrap_or_else(PoisonError::into_inner);
    // SAFETY: CSR arrays of a symmetric graph without self loops, sized as METIS expects; the
    // lock keeps other threads out of METIS's static random state meanwhile.
    let status = unsafe {
        metis_sys::METIS_NodeND(
            &mut nv,
            xadj.as_mut_ptr(),
            adjncy.as_mut_ptr(),
            std::ptr::null_mut(),
            std::ptr::null_mut(),
            perm.as_mut_ptr(),
            iperm.as_mut_ptr(),
        )
    };
    (status == metis_sys::rstatus_et_METIS_OK)
        .then(|| perm.into_iter().map(|p| p as usize).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constrained_variables_come_last_and_everything_once() {
        // A chain 0-1-2-3-4 with 0 and 4 marked last.
        let affected = [0, 1, 2, 3, 4];
        let mut last = vec![false; 5];
        last[0] = true;
        last[4] = true;
        let mut local = vec![0; 5];
        let order = order_affected(
            &affected,
            |v, out| {
                if v > 0 {
                    out.push(v - 1);
                }
                if v < 4 {
                    out.push(v + 1);
                }
            },
            &[vec![1, 3]],
            &last,
            &[3; 5],
            &mut local,
            &mut TrialHistory::default(),
        );
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, vec![0, 1, 2, 3, 4]);
        assert!(order[3..].contains(&0) && order[3..].contains(&4));
    }

    /// The adjacency of a `side` × `side` grid, vertex `r · side + c` at row `r`, column `c`.
    fn grid(side: usize) -> Vec<Vec<usize>> {
        let index = |r: usize, c: usize| r * side + c;
        let mut adjacency = vec![Vec::new(); side * side];
        for r in 0..side {
            for c in 0..side {
                if r + 1 < side {
                    adjacency[index(r, c)].push(index(r + 1, c));
                    adjacency[index(r + 1, c)].push(index(r, c));
                }
                if c + 1 < side {
                    adjacency[index(r, c)].push(index(r, c + 1));
                    adjacency[index(r, c + 1)].push(index(r, c));
                }
            }
        }
        adjacency
    }

    #[test]
    fn a_part_below_the_size_keeps_amds_order() {
        // A 40 × 40 grid of 6-dim variables (1 600, below NESTED_DISSECTION_FROM): METIS would
        // need fewer flops (the next test's kind of grid), but is not tried.
        let side = 40;
        let adjacency = grid(side);
        let n = side * side;
        assert!(n < NESTED_DISSECTION_FROM);
        let last: Vec<bool> = (0..n).map(|v| v >= n - side).collect();
        let mut trials = TrialHistory::default();
        let order = order_whole_graph(&adjacency, &last, 6, &mut trials);
        assert_eq!(order, amd_order(&adjacency, &last));
        assert!(!trials.expects_trial(n));
    }

    #[test]
    fn a_large_part_gets_the_order_with_fewer_flops() {
        // A 50 × 50 grid of 6-dim variables, far above the flops-per-variable threshold,
        // its last row constrained last. Nested dissection beats AMD on a grid this size,
        // so the kept order must need fewer flops than AMD's.
        let side = 50;
        let adjacency = grid(side);
        let n = side * side;
        let last: Vec<bool> = (0..n).map(|v| v >= n - side).collect();
        let order = order_whole_graph(&adjacency, &last, 6, &mut TrialHistory::default());
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..n).collect::<Vec<_>>());
        assert!(order[n - side..].iter().all(|&v| last[v]));
        let kept = elimination_flops(&adjacency, &order, |_| 6);
        let amd = elimination_flops(&adjacency, &amd_order(&adjacency, &last), |_| 6);
        assert!(
            amd >= NESTED_DISSECTION_ABOVE_FLOPS_PER_VARIABLE * n as f64,
            "{amd}"
        );
        assert!(kept < amd, "kept {kept} flops, AMD {amd}");
    }

    #[test]
    fn a_trial_started_beside_amd_keeps_the_order_of_one_run_after_it() {
        // METIS started at once (the history expects a trial) must give the order the trial
        // decided on AMD's flops gives: on a grid of 6-dim variables the trial runs and wins;
        // on a larger grid of 1-dim variables it is not worth trying, and AMD's order stays
        // although METIS's needs fewer flops there.
        for (side, dim) in [(50, 6), (60, 1)] {
            let adjacency = grid(side);
            let n = side * side;
            let last: Vec<bool> = (0..n).map(|v| v + side >= n).collect();
            let order_with =
                |trials: &mut TrialHistory| order_whole_graph(&adjacency, &last, dim, trials);
            let mut fresh = TrialHistory::default();
            let after = order_with(&mut fresh);
            let mut expecting = TrialHistory::default();
            expecting.record(n, true);
            assert!(expecting.expects_trial(n));
            let beside = order_with(&mut expecting);
            assert!(
                beside == after,
                "{side} × {side}, dimension {dim}: orders differ"
            );
            // Both histories now hold what this part needed.
            assert_eq!(fresh.expects_trial(n), dim == 6);
            assert_eq!(expecting.expects_trial(n), dim == 6);
            let by_nd = moved_last(
                nested_dissection(&adjacency).expect("METIS orders a grid"),
                &last,
            );
            let flops = |order: &[usize]| elimination_flops(&adjacency, order, |_| dim);
            // METIS's order needs fewer flops in both cases: only the trial rule tells them
            // apart.
            assert!(flops(&by_nd) < flops(&amd_order(&adjacency, &last)));
            assert_eq!(after == by_nd, dim == 6, "{side} × {side}, dimension {dim}");
        }
    }

    /// `order_affected` of every vertex of `adjacency`, each of dimension `dim`, without
    /// cliques.
    fn order_whole_graph(
        adjacency: &[Vec<usize>],
        last: &[bool],
        dim: usize,
        trials: &mut TrialHistory,
    ) -> Vec<usize> {
        let n = adjacency.len();
        let affected: Vec<usize> = (0..n).collect();
        order_affected(
            &affected,
            |v, out| out.extend(&adjacency[v]),
            &[],
            last,
            &vec![dim; n],
            &mut vec![0; n],
            trials,
        )
    }

    fn amd_order(adjacency: &[Vec<usize>], last: &[bool]) -> Vec<usize> {
        moved_last(BlockOrdering::amd_order(adjacency), last)
    }

    /// `order` with the vertices marked in `last` moved to its end (in that order otherwise).
    fn moved_last(order: Vec<usize>, last: &[bool]) -> Vec<usize> {
        let (mut order, constrained): (Vec<usize>, Vec<usize>) =
            order.into_iter().partition(|&v| !last[v]);
        order.extend(constrained);
        order
    }

    #[test]
    fn nested_dissection_orders_alike_on_concurrent_threads() {
        // Four threads ordering the same grid at once get the order one thread gets alone
        // (METIS's random state is shared by the process: unguarded, they disturb each other).
        let adjacency = grid(30);
        let alone = nested_dissection(&adjacency).expect("METIS orders a grid");
        std::thread::scope(|scope| {
            for _ in 0..4 {
                scope.spawn(|| {
                    for _ in 0..25 {
                        assert_eq!(nested_dissection(&adjacency).as_ref(), Some(&alone));
                    }
                });
            }
        });
    }

    #[test]
    fn nested_dissection_orders_a_grid_separator_last() {
        // A 20 × 20 grid, ordered as a permutation with its top separator last.
        let side = 20;
        let adjacency = grid(side);
        let order = nested_dissection(&adjacency).expect("METIS orders a grid");
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..side * side).collect::<Vec<_>>());
        // The last `side` vertices hold the top separator (about one grid line): without
        // them, the first vertex cannot reach the whole rest of the grid.
        let separator: std::collections::HashSet<usize> =
            order[order.len() - side..].iter().copied().collect();
        let start = order[0];
        let mut seen = vec![false; side * side];
        let mut stack = vec![start];
        seen[start] = true;
        while let Some(v) = stack.pop() {
            for &u in &adjacency[v] {
                if !seen[u] && !separator.contains(&u) {
                    seen[u] = true;
                    stack.push(u);
                }
            }
        }
        let reached = seen.iter().filter(|&&s| s).count();
        assert!(
            reached < side * side - side,
            "the last {side} vertices separate the grid ({reached} reached)"
        );
    }
}
