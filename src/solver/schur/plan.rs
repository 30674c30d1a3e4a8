//! Which blocks the Schur complement eliminates, and the reduced system's graph and order: a
//! property of the problem's structure, decided once per solve.

use std::borrow::Borrow;

use super::super::linearize::{free_adjacency, free_blocks};
use super::super::options::LinearSolverChoice;
use super::super::structure::BlockOrdering;
use super::choice;
use crate::problem::FactorEntry;
use crate::problem::Values;

/// Auto picks a dense reduced system up to this many scalar unknowns (≈110 BAL cameras): a dense
/// Cholesky of that size costs ~30 ms, about a sparse one's bookkeeping on a dense-ish S.
const DENSE_AUTO_MAX: usize = 1000;

/// How one solve eliminates: decided once per problem structure.
#[derive(Debug, Clone)]
pub struct SchurPlan {
    /// Order of the whole free-variable graph: eliminated blocks first, then the reduced ones in
    /// the order of `reduced`. The solve takes it out (the solvers do not read it).
    pub ordering: BlockOrdering,
    /// Number of eliminated blocks (they hold positions `0..eliminated`).
    pub eliminated: usize,
    /// The reduced system's graph and order; block `k` is full position `eliminated + k`.
    pub(super) reduced: BlockOrdering,
    pub dense: bool,
    /// S is never formed: conjugate gradients on its products ([`super::ImplicitSchur`]).
    pub implicit: bool,
    /// Why the implicit solver was chosen (empty for an explicit S).
    pub reason: String,
}

/// Plans the Schur complement for the free variables (`fixed[v]` false) whose kind is in
/// `kinds`; `None` when it does not apply (no such variable, nothing left to reduce to, or the
/// choice is plain sparse Cholesky). `explicit_limit`: the bytes an explicit S (with its
/// factor) may take before `Auto` solves it implicitly instead (see `choice`).
pub fn plan<E: Borrow<FactorEntry>>(
    factors: &[E],
    values: &Values,
    fixed: &[bool],
    kinds: &[&str],
    choice: LinearSolverChoice,
    explicit_limit: impl FnOnce() -> Option<u64>,
) -> Option<SchurPlan> {
    if kinds.is_empty() || choice == LinearSolverChoice::SparseCholesky {
        return None;
    }
    let (block_of_var, count) = free_blocks(fixed.iter().copied());
    let adjacency = free_adjacency(factors, fixed);
    let mut dims = vec![0; count];
    let mut eliminate = vec![false; count];
    for (v, block) in block_of_var.iter().enumerate() {
        let Some(b) = *block else { continue };
        let variable = values.variable(v);
        dims[b] = variable.tangent_dim();
        if kinds.contains(&variable.kind()) && !adjacency[b].iter().any(|&n| eliminate[n]) {
            eliminate[b] = true;
        }
    }
    let eliminated = eliminate.iter().filter(|&&e| e).count();
    if eliminated == 0 || eliminated == count {
        return None;
    }
    let reduced_index = reduced_index(&eliminate);
    let reduced_count = eliminate.len() - eliminated;
    let reduced_dim: usize = (0..count).filter(|&b| !eliminate[b]).map(|b| dims[b]).sum();
    let dense = match choice {
        LinearSolverChoice::DenseSchur => true,
        LinearSolverChoice::SparseSchur | LinearSolverChoice::IterativeSchur => false,
        _ => reduced_dim <= DENSE_AUTO_MAX,
    };
    let reason = match choice {
        LinearSolverChoice::IterativeSchur => {
            Some("requested (linear_solver iterative_schur)".into())
        }
        LinearSolverChoice::Auto => {
            let size = choice::ExplicitSize::of(&adjacency, &eliminate, &dims);
            choice::too_big(size.bytes(dense), explicit_limit())
                .or_else(|| size.slower_than_implicit())
        }
        _ => None,
    };
    let implicit = reason.is_some() && (0..count).all(|b| dims[b] <= 16);
    let reduced = if implicit {
        // Never factorised: no reduced graph, no fill-reducing order.
        BlockOrdering {
            adjacency: vec![Vec::new(); reduced_count],
            position: (0..reduced_count).collect(),
            block_at: (0..reduced_count).collect(),
        }
    } else if dense {
        // Every pair present, in the given order: the pattern is the dense lower triangle.
        let all = (0..reduced_count)
            .map(|x| (0..reduced_count).filter(|&y| y != x).collect())
            .collect();
        BlockOrdering {
            adjacency: all,
            position: (0..reduced_count).collect(),
            block_at: (0..reduced_count).collect(),
        }
    } else {
        BlockOrdering::amd(reduced_graph(&adjacency, &eliminate, &reduced_index))
    };
    let (position, block_at) = full_order(&eliminate, &reduced_index, &reduced);
    Some(SchurPlan {
        ordering: BlockOrdering {
            adjacency,
            position,
            block_at,
        },
        eliminated,
        reduced,
        dense: dense && !implicit,
        implicit,
        reason: if implicit {
            reason.unwrap_or_default()
        } else {
            String::new()
        },
    })
}

/// Each kept block's index in the reduced graph (`usize::MAX` for the eliminated).
fn reduced_index(eliminate: &[bool]) -> Vec<usize> {
    let mut next = 0;
    eliminate
        .iter()
        .map(|&e| {
            if e {
                usize::MAX
            } else {
                next += 1;
                next - 1
            }
        })
        .collect()
}

/// The reduced graph: direct neighbours, plus every pair of blocks sharing an eliminated one.
fn reduced_graph(
    adjacency: &[Vec<usize>],
    eliminate: &[bool],
    reduced_index: &[usize],
) -> Vec<Vec<usize>> {
    let count = eliminate.len();
    let kept = reduced_index.iter().filter(|&&i| i != usize::MAX).count();
    let mut reduced_adjacency = vec![Vec::new(); kept];
    for b in 0..count {
        if eliminate[b] {
            let around: Vec<usize> = adjacency[b].iter().map(|&n| reduced_index[n]).collect();
            for &x in &around {
                reduced_adjacency[x].extend(around.iter().filter(|&&y| y != x));
            }
        } else {
            reduced_adjacency[reduced_index[b]].extend(
                adjacency[b]
                    .iter()
                    .filter(|&&n| !eliminate[n])
                    .map(|&n| reduced_index[n]),
            );
        }
    }
    for list in &mut reduced_adjacency {
        list.sort_unstable();
        list.dedup();
    }
    reduced_adjacency
}

/// The whole problem's order: the eliminated blocks first (in block order), then the kept ones
/// in the reduced system's order. Returns (position of each block, block at each position).
fn full_order(
    eliminate: &[bool],
    reduced_index: &[usize],
    reduced: &BlockOrdering,
) -> (Vec<usize>, Vec<usize>) {
    let count = eliminate.len();
    let eliminated = eliminate.iter().filter(|&&e| e).count();
    let mut position = vec![0; count];
    let mut next_eliminated = 0;
    for b in 0..count {
        position[b] = if eliminate[b] {
            next_eliminated += 1;
            next_eliminated - 1
        } else {
            eliminated + reduced.position[reduced_index[b]]
        };
    }
    let mut block_at = vec![0; count];
    for (b, &p) in position.iter().enumerate() {
        block_at[p] = b;
    }
    (position, block_at)
}
