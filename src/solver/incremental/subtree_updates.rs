//! What a kept subtree contributes to the part of the factor an update eliminates again, kept
//! between updates: the multifrontal *update matrix* of the subtree's root (iSAM2's cached
//! factor of an orphan clique).
//!
//! When an update refactors the set `T` (touched variables and their ancestors), each untouched
//! subtree hanging off `T` is kept as it is, and its columns `k` still reach rows in `T`.
//! Left-looking elimination subtracts `L_{·k} L_rkᵀ` for every such column at every update. But
//! a kept subtree with root `g` only ever reaches the rows of `g` itself (`S`, all in `T`: a
//! column's structure, less its parent, lies within its parent's), and its columns do not change
//! while `g` is kept, so their sum
//!
//! ```text
//!     U_g = Σ_{k ∈ subtree(g)} L_{S,k} L_{S,k}ᵀ        (|S|×|S| blocks, symmetric)
//! ```
//!
//! is the same at every update that keeps `g`. It is computed once (from the columns of the
//! subtree that reach `S`, the cost of one left-looking pass) and afterwards added as one dense
//! matrix: the refactored part of a large map then costs its own columns and one `U` per kept
//! subtree, not every column on the border of every kept subtree again. `U_g` stays valid until
//! `g` itself is refactored (any change below `g` refactors `g`: the refactored set is closed
//! under ancestors); ranks may change, so blocks are kept per variable, not per rank.
//!
//! The store is bounded: beyond its byte budget the least recently used are dropped (they are
//! computed again when next needed). Only subtrees of at least two reaching columns are kept: a
//! single column's contribution costs no more to take from the column itself.

use std::collections::HashMap;

use super::block_factor::Accumulator;
use super::dense;

/// Bytes the store may always hold, whatever the factor's size (the dense fronts' kept buffers
/// have the same floor, see `block_factor::front`).
pub(super) const BASE_BUDGET: usize = 16 << 20;

/// `−U_g` of one kept subtree root `g`, its lower block triangle in the order of `rows`.
#[derive(Debug)]
struct SubtreeUpdate {
    /// `S`: the variables of the root's rows.
    rows: Vec<u32>,
    /// Start in `values` of block `(q, p)`, `q ≥ p`, at `q (q + 1) / 2 + p`.
    block_at: Vec<u32>,
    values: Vec<f64>,
    last_used: u64,
}

impl SubtreeUpdate {
    fn bytes(&self) -> usize {
        8 * self.values.len() + 4 * (self.rows.len() + self.block_at.len()) + 96
    }

    fn block(&self, q: usize, p: usize) -> usize {
        self.block_at[q * (q + 1) / 2 + p] as usize
    }

    /// `−= L_{S,k} L_{S,k}ᵀ` of one column `k`, whose blocks in `S` are `within` (position in
    /// `S`, offset in the column): where computing an update matrix spends its time, so
    /// compiled with AVX2 + FMA where the CPU has them (see `solver::simd`).
    fn subtract_column(&mut self, within: &[(usize, usize)], column: &ColumnView, dims: &[usize]) {
        if crate::solver::simd::has_wide_vectors() {
            // SAFETY: the CPU has the features `subtract_column_wide` is compiled for.
            unsafe { self.subtract_column_wide(within, column, dims) }
        } else {
            self.subtract_column_with::<false>(within, column, dims)
        }
    }

    #[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma"))]
    fn subtract_column_wide(
        &mut self,
        within: &[(usize, usize)],
        column: &ColumnView,
        dims: &[usize],
    ) {
        self.subtract_column_with::<true>(within, column, dims)
    }

    #[inline(always)]
    fn subtract_column_with<const FUSED: bool>(
        &mut self,
        within: &[(usize, usize)],
        column: &ColumnView,
        dims: &[usize],
    ) {
        let dk = column.dim;
        for &(qa, oa) in within {
            let da = dims[self.rows[qa] as usize];
            let l_a = &column.blocks[oa..oa + da * dk];
            for &(qb, ob) in within {
                if qb > qa {
                    continue;
                }
                let db = dims[self.rows[qb] as usize];
                let l_b = &column.blocks[ob..ob + db * dk];
                let at = self.block(qa, qb);
                dense::sub_mul_transpose::<FUSED>(&mut self.values[at..], l_a, l_b, da, db, dk);
            }
        }
    }
}

/// The kept update matrices, by subtree root.
#[derive(Debug, Default)]
pub struct SubtreeUpdates {
    entries: HashMap<u32, SubtreeUpdate>,
    bytes: usize,
    clock: u64,
}

/// A column of `L` as the store reads it: its rows `(variable, offset in blocks)` and blocks.
pub struct ColumnView<'a> {
    pub dim: usize,
    pub rows: &'a [(u32, u32)],
    pub blocks: &'a [f64],
}

impl SubtreeUpdates {
    /// Bytes held (counted in the session's memory).
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    pub fn contains(&self, root: usize) -> bool {
        self.entries.contains_key(&(root as u32))
    }

    /// `root`'s column is eliminated again: what its subtree contributed is no longer known.
    pub fn forget(&mut self, root: usize) {
        if let Some(old) = self.entries.remove(&(root as u32)) {
            self.bytes -= old.bytes();
        }
    }

    /// Computes and keeps `U` of the subtree rooted at `root` (whose rows are `rows`) from the
    /// columns of that subtree that reach those rows (`reaching`, `root` among them). `slot` is
    /// scratch indexed by variable, `u32::MAX` everywhere (and left so).
    pub fn compute<'a>(
        &mut self,
        root: usize,
        rows: Vec<u32>,
        reaching: impl Iterator<Item = ColumnView<'a>>,
        dims: &[usize],
        slot: &mut [u32],
    ) {
        for (q, &u) in rows.iter().enumerate() {
            slot[u as usize] = q as u32;
        }
        let m = rows.len();
        let mut block_at = Vec::with_capacity(m * (m + 1) / 2);
        let mut len = 0usize;
        for q in 0..m {
            for p in 0..=q {
                block_at.push(len as u32);
                len += dims[rows[q] as usize] * dims[rows[p] as usize];
            }
        }
        let mut update = SubtreeUpdate {
            rows,
            block_at,
            values: vec![0.0; len],
            last_used: self.clock,
        };
        let mut within: Vec<(usize, usize)> = Vec::new();
        for column in reaching {
            within.clear();
            within.extend(
                column
                    .rows
                    .iter()
                    .filter(|&&(u, _)| slot[u as usize] != u32::MAX)
                    .map(|&(u, o)| (slot[u as usize] as usize, o as usize)),
            );
            update.subtract_column(&within, &column, dims);
        }
        for &u in &update.rows {
            slot[u as usize] = u32::MAX;
        }
        self.bytes += update.bytes();
        if let Some(old) = self.entries.insert(root as u32, update) {
            self.bytes -= old.bytes();
        }
    }

    /// Adds `root`'s `−U` to the column being eliminated (in `acc`), the root's row at position
    /// `p`: the diagonal block, and block `(u, r)` for every other row `u` of `root` that
    /// `later(u)` (eliminated after it).
    pub fn subtract_from_column(
        &mut self,
        root: usize,
        p: usize,
        dims: &[usize],
        acc: &mut Accumulator,
        later: impl Fn(usize) -> bool,
    ) {
        let clock = self.clock;
        let update = self
            .entries
            .get_mut(&(root as u32))
            .expect("a kept update is applied only after it was computed");
        update.last_used = clock;
        let d = dims[update.rows[p] as usize];
        let at = update.block(p, p);
        let diagonal = &update.values[at..at + d * d];
        for (out, v) in acc.diagonal_mut().iter_mut().zip(diagonal) {
            *out += v;
        }
        for (q, &u) in update.rows.iter().enumerate() {
            let u = u as usize;
            if q == p || !later(u) {
                continue;
            }
            let du = dims[u];
            let out = acc.block_mut(u, du);
            if q > p {
                let at = update.block(q, p);
                for (o, v) in out.iter_mut().zip(&update.values[at..at + du * d]) {
                    *o += v;
                }
            } else {
                // Only (p, q) is kept: its transpose.
                let stored = &update.values[update.block(p, q)..];
                for i in 0..du {
                    for j in 0..d {
                        out[i * d + j] += stored[j * du + i];
                    }
                }
            }
        }
    }

    /// One refactor is over: drops the least recently used beyond the budget (the factor's own
    /// size, and at least `BASE_BUDGET`).
    pub fn end_refactor(&mut self, factor_bytes: usize) {
        self.clock += 1;
        let budget = BASE_BUDGET.max(factor_bytes);
        if self.bytes <= budget {
            return;
        }
        let mut by_age: Vec<(u64, u32)> = self
            .entries
            .iter()
            .map(|(&g, e)| (e.last_used, g))
            .collect();
        by_age.sort_unstable();
        for (_, g) in by_age {
            if self.bytes <= budget {
                break;
            }
            self.forget(g as usize);
        }
    }
}
