//! Which closures between two components agree: pairwise consistency and the largest set of
//! closures that all agree with each other (PCM, Mangelson et al. 2018, with the whitened
//! closure error standing in for its Mahalanobis distance).
//!
//! Closure `k` implies a frame transform `T_k` between the components (see `frame`). Closures
//! `k` and `l` agree when each one's error, with the far component moved by the other's
//! transform, stays within the χ² quantile of its dimension at 99.9 %, widened by the odometry
//! between them: each component's estimate drifts between two of its poses, the more the more
//! odometry steps (poses of one robot apart in key order) lie between them. A wrong closure
//! implies a transform metres or radians away from the true one, a χ² of thousands; the
//! largest mutually consistent set is the consensus, and a merge needs enough of them.

use crate::solver::chi_square::cached_quantile;
use crate::variables::frame::Frame;

/// At most this many closures per pair of components take part (the newest): the exact
/// maximum-clique search is exponential in the worst case, and a merge needs only a few.
pub(crate) const MAX_CANDIDATES: usize = 48;

/// Odometry steps assumed between poses of two different robots on one side (a merged
/// component): their relative placement is as uncertain as a long chain of odometry.
pub(crate) const STEPS_ACROSS_ROBOTS: u64 = 200;

/// One closure as the consensus sees it.
pub(crate) struct Candidate {
    /// The transform it implies (`kept ← moved`).
    pub implied: Frame,
    /// Its residual dimension (the χ² quantile's degrees of freedom).
    pub dof: usize,
    /// Where it attaches on each side: (robot, pose index), `None` for a key of no robot.
    pub ends: [Option<(u8, u64)>; 2],
}

/// The odometry steps between where `a` and `b` attach, summed over both sides.
pub(crate) fn steps_between(a: &Candidate, b: &Candidate) -> u64 {
    (0..2)
        .map(|side| match (a.ends[side], b.ends[side]) {
            (Some((ra, ia)), Some((rb, ib))) if ra == rb => ia.abs_diff(ib),
            _ => STEPS_ACROSS_ROBOTS,
        })
        .sum()
}

/// Whether closures `i` and `j` agree; `chi2(i, t)`: closure `i`'s whitened squared error with
/// the moved component placed by `t` (`None`: it could not be evaluated, so no agreement).
pub(crate) fn agree(
    candidates: &[Candidate],
    i: usize,
    j: usize,
    chi2: &mut dyn FnMut(usize, &Frame) -> Option<f64>,
) -> bool {
    let (a, b) = (&candidates[i], &candidates[j]);
    let widen = 1.0 + steps_between(a, b) as f64;
    let fits =
        |k: usize, dof: usize, t: &Frame, chi2: &mut dyn FnMut(usize, &Frame) -> Option<f64>| {
            chi2(k, t).is_some_and(|c| c <= cached_quantile(dof, 0.999) * widen)
        };
    fits(i, a.dof, &b.implied, chi2) && fits(j, b.dof, &a.implied, chi2)
}

/// The largest set of candidates that all agree pairwise (ties: the one found first, which
/// prefers lower indices), as indices in increasing order.
pub(crate) fn largest_consistent_set(
    n: usize,
    agree: &mut dyn FnMut(usize, usize) -> bool,
) -> Vec<usize> {
    assert!(n <= 64, "at most 64 candidates (bit sets)");
    let mut adjacent = vec![0u64; n];
    for i in 0..n {
        for j in i + 1..n {
            if agree(i, j) {
                adjacent[i] |= 1 << j;
                adjacent[j] |= 1 << i;
            }
        }
    }
    let all = if n == 64 { u64::MAX } else { (1u64 << n) - 1 };
    let mut best = 0u64;
    bron_kerbosch(&adjacent, 0, all, 0, &mut best);
    (0..n).filter(|i| best & (1 << i) != 0).collect()
}

/// Bron–Kerbosch with pivoting over bit sets: `r` the clique so far, `p` the candidates that
/// extend it, `x` those already tried.
fn bron_kerbosch(adjacent: &[u64], r: u64, mut p: u64, mut x: u64, best: &mut u64) {
    if p == 0 {
        if x == 0 && r.count_ones() > best.count_ones() {
            *best = r;
        }
        return;
    }
    // No extension of `r` can beat `best`.
    if r.count_ones() + p.count_ones() <= best.count_ones() {
        return;
    }
    let pivot = (p | x).trailing_zeros() as usize;
    let mut rest = p & !adjacent[pivot];
    while rest != 0 {
        let v = rest.trailing_zeros() as usize;
        rest &= rest - 1;
        bron_kerbosch(
            adjacent,
            r | (1 << v),
            p & adjacent[v],
            x & adjacent[v],
            best,
        );
        p &= !(1 << v);
        x |= 1 << v;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Se2;

    #[test]
    fn the_largest_set_that_agrees_pairwise_wins() {
        // 0-1-2 agree with each other, 3-4 with each other, 5 with nobody.
        let pairs = [(0, 1), (0, 2), (1, 2), (3, 4), (2, 3)];
        let mut agree = |i: usize, j: usize| pairs.contains(&(i.min(j), i.max(j)));
        assert_eq!(largest_consistent_set(6, &mut agree), vec![0, 1, 2]);
        let mut none = |_: usize, _: usize| false;
        assert_eq!(largest_consistent_set(3, &mut none).len(), 1);
        assert!(largest_consistent_set(0, &mut none).is_empty());
    }

    #[test]
    fn closures_agree_when_their_transforms_fit_each_other() {
        let at = |x: f64, theta: f64, index: u64| Candidate {
            implied: Frame::Planar(Se2::new(x, 0.0, theta)),
            dof: 3,
            ends: [Some((b'a', index)), Some((b'b', index))],
        };
        let candidates = [at(5.0, 0.1, 10), at(5.01, 0.1, 12), at(9.0, -1.0, 11)];
        // χ² as if each closure had unit noise: the squared distance of the transforms.
        let mut chi2 = |k: usize, t: &Frame| {
            let (dt, dr) = candidates[k].implied.distance(t)?;
            Some((dt / 0.05).powi(2) + (dr / 0.01).powi(2))
        };
        assert!(agree(&candidates, 0, 1, &mut chi2));
        assert!(!agree(&candidates, 0, 2, &mut chi2));
        assert_eq!(steps_between(&candidates[0], &candidates[1]), 4);
    }
}
