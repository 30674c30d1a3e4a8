//! Gauge freedom: a pose graph with only relative measurements can slide and turn as a whole.
//! Every connected component of the factor graph that has neither a fixed variable nor a unary
//! factor (a prior) gets its lowest-keyed pose fixed for the solve, and the Summary says which.

use super::union_find::find_root as find;
use crate::problem::FactorEntry;
use crate::problem::{Key, Values};

/// Returns the per-variable fixed flags to solve with, and the keys fixed automatically.
pub fn anchor_components<E: std::borrow::Borrow<FactorEntry>>(
    factors: &[E],
    values: &Values,
) -> (Vec<bool>, Vec<Key>) {
    let n = values.len();
    let mut parent: Vec<usize> = (0..n).collect();
    // A fixed variable or a unary factor (a prior) anchors its component.
    let mut anchored: Vec<bool> = (0..n).map(|v| values.is_fixed(v)).collect();
    for f in factors {
        let idx = f.borrow().variables();
        if let [only] = idx {
            anchored[*only] = true;
        }
        for w in idx.windows(2) {
            let (a, b) = (find(&mut parent, w[0]), find(&mut parent, w[1]));
            if a != b {
                parent[a] = b;
            }
        }
    }
    let mut root_anchored = vec![false; n];
    for (v, _) in anchored.iter().enumerate().filter(|(_, &a)| a) {
        let r = find(&mut parent, v);
        root_anchored[r] = true;
    }
    // Lowest key of each unanchored component among its variables of the largest tangent
    // dimension: a pose, not a landmark (fixing a 2D landmark would leave the map free to turn).
    let rank = |v: usize| {
        (
            std::cmp::Reverse(values.variable(v).tangent_dim()),
            values.key(v),
        )
    };
    let mut lowest: Vec<Option<usize>> = vec![None; n];
    for v in 0..n {
        let r = find(&mut parent, v);
        if !root_anchored[r] && lowest[r].is_none_or(|u| rank(v) < rank(u)) {
            lowest[r] = Some(v);
        }
    }
    let mut fixed: Vec<bool> = (0..n).map(|v| values.is_fixed(v)).collect();
    let mut keys = Vec::new();
    for v in lowest.into_iter().flatten() {
        fixed[v] = true;
        keys.push(values.key(v));
    }
    keys.sort_unstable();
    (fixed, keys)
}
