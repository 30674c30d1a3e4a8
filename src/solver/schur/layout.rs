//! Where every piece of the elimination lives, decided once per structure: per eliminated block
//! its V⁻¹ and the S block of every neighbour pair; the U entries
//! copied into S; and the reduced system's backend (dense buffer or sparse symbolic analysis).

use super::super::budget::FactorCost;
use super::super::cholesky::SymbolicError;
use super::super::structure::BlockPattern;
use super::reduced::Backend;
use super::{EliminatedBlocks, Neighbour, SchurPlan, SchurSolver};

impl SchurSolver {
    /// `full` is the pattern laid out with `plan.ordering`.
    pub fn new(full: &BlockPattern, plan: &SchurPlan) -> Result<Self, SymbolicError> {
        let ne = plan.eliminated;
        // The reduced graph numbers its blocks in free-block order; full position ne + k holds
        // the block at reduced position k.
        let dims_by_block: Vec<usize> = plan
            .reduced
            .position
            .iter()
            .map(|&k| full.dim[ne + k])
            .collect();
        let reduced = BlockPattern::with_ordering(&dims_by_block, &plan.reduced);
        let n = reduced.n;
        let blocks = EliminatedBlocks::of(full, ne);
        let mut s_block_start = Vec::with_capacity(ne + 1);
        let mut s_blocks = Vec::new();
        let mut w_max = 0;
        for e in 0..ne {
            let near = blocks.neighbours_of(e);
            s_block_start.push(s_blocks.len());
            let w_len: usize = near.iter().map(|nb| full.dim[ne + nb.block]).sum();
            w_max = w_max.max(w_len * blocks.dim[e]);
            push_s_blocks(&reduced, plan.dense, near, &mut s_blocks);
        }
        s_block_start.push(s_blocks.len());
        let u_map = u_map(full, &reduced, ne, plan.dense);
        let backend = Backend::new(&reduced, plan.dense)?;
        let s_len = backend.values_len(&reduced);
        let reduced_cost = FactorCost {
            flops: backend.factor_flops(&reduced),
            measured_rate: None,
        };
        Ok(Self {
            eliminated: ne,
            v_inverse: vec![0.0; blocks.v_start[ne]],
            blocks,
            s_block_start,
            s_blocks,
            u_map,
            s_values: vec![0.0; s_len],
            w_local: vec![0.0; w_max],
            y_local: vec![0.0; w_max],
            rhs: vec![0.0; n],
            parts: std::iter::once(0..ne).collect(),
            helpers: Vec::new(),
            reduced,
            backend,
            reduced_cost,
        })
    }
}

/// The S block of every pair (k, l ≤ k) of one eliminated block's `neighbours`: where it starts
/// in the dense buffer, or its pair in the sparse pattern. Neighbours are sorted by position,
/// so (k, l ≤ k) is a lower block of S.
fn push_s_blocks(
    reduced: &BlockPattern,
    dense: bool,
    neighbours: &[Neighbour],
    s_blocks: &mut Vec<usize>,
) {
    for (k, nk) in neighbours.iter().enumerate() {
        for nl in &neighbours[..=k] {
            let (a, b) = (nk.block, nl.block);
            s_blocks.push(if dense {
                dense_index(reduced, a, b, 0, 0)
            } else {
                reduced
                    .pair(a, b)
                    .expect("the reduced pattern holds every pair sharing an eliminated block")
            });
        }
    }
}

/// Where element (r, q) of the S block (a ≥ b, reduced positions) lives in the dense buffer.
fn dense_index(reduced: &BlockPattern, a: usize, b: usize, r: usize, q: usize) -> usize {
    (reduced.offset[b] + q) * reduced.n + reduced.offset[a] + r
}

/// Where each U entry (between kept blocks, at `full`'s value index) is copied into S.
fn u_map(
    full: &BlockPattern,
    reduced: &BlockPattern,
    ne: usize,
    dense: bool,
) -> Vec<(usize, usize)> {
    let mut u_map = Vec::new();
    for b in ne..full.dim.len() {
        for &(a, pair) in full.column_blocks(b) {
            let diagonal = a == b;
            let (ra, rb) = (a - ne, b - ne);
            let s_pair = reduced
                .pair(ra, rb)
                .expect("the reduced pattern holds every direct pair");
            for q in 0..full.dim[b] {
                let rows = if diagonal { q } else { 0 };
                for r in rows..full.dim[a] {
                    let to = if dense {
                        dense_index(reduced, ra, rb, r, q)
                    } else {
                        reduced.value_index(s_pair, diagonal, r, q)
                    };
                    u_map.push((full.value_index(pair, diagonal, r, q), to));
                }
            }
        }
    }
    u_map
}
