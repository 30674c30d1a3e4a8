//! The 2D chordal estimate (see [`super`]): orientations unwrapped along a breadth-first tree,
//! then two scalar Laplacians over the free poses — orientations, then positions with those
//! orientations held — sharing one pattern and one symbolic factorisation.
//!
//! Both systems are sums of terms `w (x_to − x_from − c)²` (`x_from` absent for a prior), so
//! each edge adds `w` to two diagonal entries and `−w` to one off-diagonal entry whose place in
//! the pattern is found once for both systems.

use std::collections::VecDeque;
use std::f64::consts::PI;

use faer::sparse::linalg::SupernodalThreshold;
use nalgebra::Vector2;

use super::{collect_edges, marginal_information, Edge, Stoppable};
use crate::factors::{BetweenSe2, PriorSe2};
use crate::geometry::{rotation_matrix_2d, Se2};
use crate::problem::{FactorEntry, Values};
use crate::solver::cholesky::SparseCholesky;
use crate::solver::linearize::free_blocks;
use crate::solver::structure::{BlockOrdering, BlockPattern};
use crate::solver::supernodes::BlockSupernodes;

/// Where one edge's terms go: the elimination positions of its free ends and, when both are
/// free, the value index of their off-diagonal entry.
struct Slot {
    from: Option<usize>,
    to: Option<usize>,
    off: usize,
}

/// A scalar Laplacian system over the free poses, with `R` right-hand sides.
struct Laplacian<'a, const R: usize> {
    pattern: &'a BlockPattern,
    h: Vec<f64>,
    rhs: [Vec<f64>; R],
}

impl<'a, const R: usize> Laplacian<'a, R> {
    fn new(pattern: &'a BlockPattern) -> Self {
        Self {
            pattern,
            h: vec![0.0; pattern.nnz()],
            rhs: std::array::from_fn(|_| vec![0.0; pattern.n]),
        }
    }

    /// Adds `w (x_to − x_from − c)²`; `r0` is its residual at x = 0 of the free ends (the
    /// fixed ends' values folded in).
    fn add(&mut self, slot: &Slot, w: f64, r0: [f64; R]) {
        if let Some(p) = slot.to {
            self.h[self.pattern.diagonal_index(p)] += w;
            for (rhs, r) in self.rhs.iter_mut().zip(r0) {
                rhs[p] -= w * r;
            }
        }
        if let Some(p) = slot.from {
            self.h[self.pattern.diagonal_index(p)] += w;
            for (rhs, r) in self.rhs.iter_mut().zip(r0) {
                rhs[p] += w * r;
            }
        }
        if slot.to.is_some() && slot.from.is_some() {
            self.h[slot.off] -= w;
        }
    }

    /// Factorises and solves in place; `None` when singular or stopped by the budget.
    fn solve(mut self, chol: &mut SparseCholesky, budget: &Stoppable) -> Option<[Vec<f64>; R]> {
        if !budget.may_factorize(chol.factor_flops()) {
            return None;
        }
        chol.factorize(self.pattern, &self.h).ok()?;
        for rhs in self.rhs.iter_mut() {
            chol.solve_in_place(rhs);
        }
        Some(self.rhs)
    }
}

pub(super) fn chordal_2d<E: std::borrow::Borrow<FactorEntry>>(
    factors: &[E],
    values: &Values,
    fixed: &[bool],
    ordering: &BlockOrdering,
    shared: Option<&BlockSupernodes>,
    budget: &Stoppable,
    unwrap_at_values: bool,
) -> Option<Values> {
    let edges = collect_edges(
        factors,
        |f| {
            f.factor
                .as_any()
                .downcast_ref::<BetweenSe2>()
                .map(|b| b.measurement)
        },
        |f| {
            f.factor
                .as_any()
                .downcast_ref::<PriorSe2>()
                .map(|p| p.measurement)
        },
    )?;
    let n = values.len();
    let pose = |v: usize| {
        *values
            .variable(v)
            .as_any()
            .downcast_ref::<Se2>()
            .expect("checked kind")
    };
    let tree = if unwrap_at_values {
        (0..n).map(|v| pose(v).theta).collect()
    } else {
        tree_orientations(&edges, n, fixed, &pose)?
    };
    let weights = edge_weights(&edges)?;
    let (block, nb) = free_blocks(fixed.iter().copied());
    let pattern = BlockPattern::with_ordering(&vec![1; nb], ordering);
    // The solve's supernodes fit these scalar Laplacians too: no second analysis. Without
    // them, faer's heuristic picks simplicial for the Laplacians (its supernodes of single
    // columns amalgamate into blocks of mostly zeros).
    let mut chol = match shared {
        Some(blocks) => SparseCholesky::with_block_supernodes(&pattern, blocks),
        None => SparseCholesky::analyze(&pattern, SupernodalThreshold::AUTO).ok()?,
    };
    let position = |v: usize| block[v].map(|b| pattern.position[b]);
    let slots = edge_slots(&edges, &pattern, &position)?;
    // A fixed end's value, or 0 for a free end and for the world frame of a prior.
    let fixed_value = |v: Option<usize>, value: &dyn Fn(usize) -> f64| match v {
        Some(v) if fixed[v] => value(v),
        _ => 0.0,
    };

    let mut rot = Laplacian::<1>::new(&pattern);
    for ((e, slot), &(w, _)) in edges.iter().zip(&slots).zip(&weights) {
        let from_theta = e.from.map_or(0.0, |i| tree[i]);
        let k = ((tree[e.to] - from_theta - e.measurement.theta) / (2.0 * PI)).round();
        let c = e.measurement.theta + 2.0 * PI * k;
        let theta = |v: usize| tree[v];
        let r0 = fixed_value(Some(e.to), &theta) - fixed_value(e.from, &theta) - c;
        rot.add(slot, w, [r0]);
    }
    let [solved] = rot.solve(&mut chol, budget)?;
    let theta: Vec<f64> = (0..n)
        .map(|v| match position(v) {
            Some(p) => solved[p],
            None => tree[v],
        })
        .collect();

    let system = Translations {
        edges: &edges,
        slots: &slots,
        weights: &weights,
        fixed,
        pattern: &pattern,
    };
    let [x, y] = system.solve(&theta, &pose, &mut chol, budget)?;
    let mut out = values.clone();
    for (v, &heading) in theta.iter().enumerate().take(n) {
        if let Some(p) = position(v) {
            out.set(v, &Se2::new(x[p], y[p], heading));
        }
    }
    Some(out)
}

/// The positions' Laplacian, with the orientations held.
struct Translations<'a, 'e> {
    edges: &'a [Edge<'e, Se2>],
    slots: &'a [Slot],
    weights: &'a [(f64, f64)],
    fixed: &'a [bool],
    pattern: &'a BlockPattern,
}

impl Translations<'_, '_> {
    /// x and y of every free pose (by elimination position), the orientations `theta` held;
    /// `pose(v)` gives a fixed pose's position.
    fn solve(
        &self,
        theta: &[f64],
        pose: &dyn Fn(usize) -> Se2,
        chol: &mut SparseCholesky,
        budget: &Stoppable,
    ) -> Option<[Vec<f64>; 2]> {
        let fixed_value = |v: Option<usize>, value: &dyn Fn(usize) -> f64| match v {
            Some(v) if self.fixed[v] => value(v),
            _ => 0.0,
        };
        let mut trans = Laplacian::<2>::new(self.pattern);
        for ((e, slot), &(_, w)) in self.edges.iter().zip(self.slots).zip(self.weights) {
            let z = Vector2::new(e.measurement.x, e.measurement.y);
            // ‖R_iᵀ(t_j − t_i) − t_ij‖² = ‖t_j − t_i − R_i t_ij‖² under an isotropic weight.
            let c = match e.from {
                Some(i) => rotation_matrix_2d(theta[i]) * z,
                None => z,
            };
            let r0: [f64; 2] = std::array::from_fn(|axis| {
                let coordinate = |v: usize| {
                    let p = pose(v);
                    if axis == 0 {
                        p.x
                    } else {
                        p.y
                    }
                };
                fixed_value(Some(e.to), &coordinate) - fixed_value(e.from, &coordinate) - c[axis]
            });
            trans.add(slot, w, r0);
        }
        trans.solve(chol, budget)
    }
}

/// Each edge's weights: for the rotation, the marginal information of θ; for the translation,
/// isotropic, the mean eigenvalue of the marginal translation information, so both steps are
/// scalar Laplacians over one graph.
fn edge_weights(edges: &[Edge<'_, Se2>]) -> Option<Vec<(f64, f64)>> {
    edges
        .iter()
        .map(|e| {
            let wt = marginal_information::<3, 2>(e.sqrt_information, 0)?.trace() / 2.0;
            Some((
                marginal_information::<3, 1>(e.sqrt_information, 2)?[(0, 0)],
                wt,
            ))
        })
        .collect()
}

/// Where each edge lands in the Laplacians: its ends' positions (free ends only) and the
/// off-diagonal entry they share.
fn edge_slots(
    edges: &[Edge<'_, Se2>],
    pattern: &BlockPattern,
    position: &dyn Fn(usize) -> Option<usize>,
) -> Option<Vec<Slot>> {
    edges
        .iter()
        .map(|e| {
            let (from, to) = (e.from.and_then(position), position(e.to));
            let off = match (from, to) {
                (Some(a), Some(b)) => {
                    let pair = pattern.pair(a.max(b), a.min(b))?;
                    pattern.value_index(pair, false, 0, 0)
                }
                _ => 0,
            };
            Some(Slot { from, to, off })
        })
        .collect()
}

/// Unwrapped orientations along a breadth-first spanning tree from the anchors (fixed
/// variables, then priors); 0 where no anchor reaches.
fn tree_orientations(
    edges: &[Edge<'_, Se2>],
    n: usize,
    fixed: &[bool],
    pose: &dyn Fn(usize) -> Se2,
) -> Option<Vec<f64>> {
    // Neighbours with the measured rotation towards them, in compressed rows.
    let mut start = vec![0usize; n + 1];
    for e in edges {
        if let Some(i) = e.from {
            start[i + 1] += 1;
            start[e.to + 1] += 1;
        }
    }
    for v in 0..n {
        start[v + 1] += start[v];
    }
    let mut next = start.clone();
    let mut neighbours = vec![(0usize, 0.0f64); start[n]];
    for e in edges {
        if let Some(i) = e.from {
            neighbours[next[i]] = (e.to, e.measurement.theta);
            next[i] += 1;
            neighbours[next[e.to]] = (i, -e.measurement.theta);
            next[e.to] += 1;
        }
    }
    let mut tree: Vec<Option<f64>> = vec![None; n];
    let mut queue = VecDeque::new();
    for v in 0..n {
        if fixed[v] {
            tree[v] = Some(pose(v).theta);
            queue.push_back(v);
        }
    }
    for e in edges {
        if e.from.is_none() && tree[e.to].is_none() {
            tree[e.to] = Some(e.measurement.theta);
            queue.push_back(e.to);
        }
    }
    // Breadth-first: shortest paths accumulate the least rotation noise into the unwrapping.
    while let Some(i) = queue.pop_front() {
        let ti = tree[i]?;
        for &(j, d) in &neighbours[start[i]..start[i + 1]] {
            if tree[j].is_none() {
                tree[j] = Some(ti + d);
                queue.push_back(j);
            }
        }
    }
    Some(tree.into_iter().map(|t| t.unwrap_or(0.0)).collect())
}

#[cfg(test)]
mod tests {
    use std::cell::Cell;

    use nalgebra::DMatrix;

    use super::super::chordal;
    use super::*;
    use crate::factors::{BetweenSe2, PriorSe2};
    use crate::geometry::wrap_angle;
    use crate::problem::Problem;
    use crate::solver::linearize::free_adjacency;
    use crate::solver::Unlimited;

    /// Consistent measurements have an exact chordal estimate, from any start: poses on a loop
    /// whose headings cross ±π (the unwrapping), odometry and loop closures with correlated
    /// anisotropic information, one fixed pose and one prior as anchors.
    #[test]
    fn recovers_a_noiseless_graph_across_the_angle_wrap() {
        let truth: Vec<Se2> = (0..8)
            .map(|k| {
                let a = k as f64 * 0.8;
                Se2::new(3.0 * a.cos(), 2.0 * a.sin(), wrap_angle(a + 2.9))
            })
            .collect();
        let mut problem = Problem::new();
        for (k, pose) in truth.iter().enumerate() {
            let start = if k == 0 {
                *pose
            } else {
                Se2::new(0.0, 0.0, 0.0)
            };
            problem.add_variable(k as u64, Box::new(start)).unwrap();
        }
        problem.set_fixed(0, true).unwrap();
        let information =
            DMatrix::from_row_slice(3, 3, &[50.0, 10.0, 2.0, 10.0, 30.0, 1.0, 2.0, 1.0, 400.0]);
        let pairs = [
            (0, 1),
            (1, 2),
            (2, 3),
            (3, 4),
            (4, 5),
            (5, 6),
            (6, 7),
            (0, 4),
            (2, 7),
            (7, 0),
        ];
        for (i, j) in pairs {
            let z = truth[i].between(&truth[j]);
            let factor = BetweenSe2::new(i as u64, j as u64, z);
            problem
                .add_factor(Box::new(factor), &information, None, "odometry")
                .unwrap();
        }
        let prior = PriorSe2::new(5, truth[5]);
        problem
            .add_factor(Box::new(prior), &information, None, "prior")
            .unwrap();

        let fixed: Vec<bool> = (0..truth.len())
            .map(|v| problem.values.is_fixed(v))
            .collect();
        let ordering = BlockOrdering::amd(free_adjacency(problem.factors(), &fixed));
        // With faer's own analysis of the Laplacians, and with the solve's supernodes shared.
        let solve_pattern = BlockPattern::with_ordering(&[3; 7], &ordering);
        let solve_supernodes = BlockSupernodes::analyze(&solve_pattern);
        for shared in [None, Some(&solve_supernodes)] {
            let stopped = Cell::new(false);
            let budget = Stoppable {
                budget: &Unlimited,
                stopped: &stopped,
            };
            let estimate = chordal(
                problem.factors(),
                &problem.values,
                &fixed,
                &ordering,
                shared,
                &budget,
            )
            .expect("a pose graph has a chordal estimate");
            for (k, pose) in truth.iter().enumerate() {
                let got = estimate.variable(k).as_any().downcast_ref::<Se2>().unwrap();
                assert!(
                    (got.x - pose.x).abs() < 1e-9,
                    "x of {k}: {} vs {}",
                    got.x,
                    pose.x
                );
                assert!(
                    (got.y - pose.y).abs() < 1e-9,
                    "y of {k}: {} vs {}",
                    got.y,
                    pose.y
                );
                let dtheta = wrap_angle(got.theta - pose.theta);
                assert!(
                    dtheta.abs() < 1e-9,
                    "theta of {k}: {} vs {}",
                    got.theta,
                    pose.theta
                );
            }
        }
    }
}
