//! The block Cholesky factor `L` of the normal equations that a session keeps between updates,
//! with its elimination tree.
//!
//! Column `v` of `L` (one per free variable) holds the diagonal block `L_vv` and the blocks
//! `L_uv` of the variables `u` eliminated after `v` that it reaches. The order is a *rank* per
//! variable; an update gives fresh ranks, above every other, to the columns it eliminates
//! again. Why only those change (the argument of iSAM2's Bayes tree, Kaess et al. 2012): a
//! column depends only on `H`'s entries in its own subtree of the elimination tree and on the
//! columns of that subtree. An update changes `H` at the variables it touches, so exactly their
//! columns and those of their ancestors (the path to the root) change; every other column keeps
//! its values and its row structure (its neighbours eliminated before it are its descendants, so
//! they stay before it, and its ancestors, wherever they move, stay after it).
//!
//! Elimination is left-looking: column `r` is `H`'s column minus `Σ_k L_{·k} L_rkᵀ` over the
//! columns `k` that reach row `r` (kept per row in `row_columns`), so the refactored part takes
//! the untouched subtrees' contributions straight from their stored columns.

use std::collections::BTreeSet;

use super::dense;
use super::subtree_updates::{ColumnView, SubtreeUpdates};
use crate::solver::schur::small_cholesky;
use front::FrontUpdates;

const NONE: u32 = u32::MAX;
/// A zero block of the largest variable (15-dimensional navigation states).
const ZEROS: [f64; 15 * 15] = [0.0; 15 * 15];

/// Where the update matrices of kept subtrees apply, `(rank of a refactored column, subtree
/// root, position of that column among the root's rows)` sorted by rank, and the next one to
/// apply.
struct KeptApplications {
    list: Vec<(u64, u32, u32)>,
    next: usize,
}

/// One column of `L`.
#[derive(Debug, Default, Clone)]
pub struct Column {
    /// `L_vv`, d×d lower triangular, row-major.
    pub diagonal: Vec<f64>,
    /// `(u, offset)`: block `L_uv` (d_u × d_v, row-major) starts at `blocks[offset]`.
    pub rows: Vec<(u32, u32)>,
    pub blocks: Vec<f64>,
}

/// Where a column's `H` entries are gathered while it is eliminated.
#[derive(Debug, Default)]
pub struct Accumulator {
    dim: usize,
    diagonal: Vec<f64>,
    slot: Vec<u32>,
    entries: Vec<(u32, u32)>,
    buffer: Vec<f64>,
    /// `−L_rr⁻¹` and a block's copy, while the column's blocks are scaled.
    inverse: Vec<f64>,
    scratch: Vec<f64>,
}

impl Accumulator {
    fn start(&mut self, dim: usize, variables: usize) {
        self.dim = dim;
        self.diagonal.clear();
        self.diagonal.resize(dim * dim, 0.0);
        self.slot.resize(variables, NONE);
        self.entries.clear();
        self.buffer.clear();
    }

    /// The diagonal block (d×d, row-major; only its lower triangle is read).
    pub fn diagonal_mut(&mut self) -> &mut [f64] {
        &mut self.diagonal
    }

    /// Block `(u, v)` of the column being eliminated, `du × d_v`, created zero on first use.
    pub fn block_mut(&mut self, u: usize, du: usize) -> &mut [f64] {
        let d = self.dim;
        if self.slot[u] == NONE {
            self.slot[u] = self.entries.len() as u32;
            self.entries.push((u as u32, self.buffer.len() as u32));
            match ZEROS.get(..du * d) {
                Some(zeros) => self.buffer.extend_from_slice(zeros),
                None => self.buffer.resize(self.buffer.len() + du * d, 0.0),
            }
        }
        let offset = self.entries[self.slot[u] as usize].1 as usize;
        &mut self.buffer[offset..offset + du * d]
    }

    fn finish(&mut self) {
        for &(u, _) in &self.entries {
            self.slot[u as usize] = NONE;
        }
    }
}

/// The factor, its order and its elimination tree. Variables are the problem's dense indices;
/// a variable of dimension 0 (fixed, or not yet added) has no column.
#[derive(Debug, Default)]
pub struct BlockFactor {
    pub dim: Vec<usize>,
    /// Elimination order: a variable's column comes after every column of lower rank.
    pub rank: Vec<u64>,
    next_rank: u64,
    pub columns: Vec<Column>,
    /// For each variable `u`, the columns `k` with a block `L_uk` (its row's structure), with
    /// that block's offset in column `k` (a column keeps its blocks until it is refactored, and
    /// then registers them again).
    row_columns: Vec<Vec<(u32, u32)>>,
    parent: Vec<u32>,
    children: Vec<Vec<u32>>,
    roots: BTreeSet<u32>,
    accumulator: Accumulator,
    changed: Vec<bool>,
    /// Scalar nonzeros of L.
    nnz: usize,
    /// What kept subtrees contribute to a refactored part (see `subtree_updates`).
    kept: SubtreeUpdates,
    /// During a refactor: the columns whose contribution comes from their kept subtree's
    /// update matrix, and each visited kept column's subtree root (scratch, else clear).
    covered: Vec<bool>,
    kept_root: Vec<u32>,
    slot: Vec<u32>,
    /// Columns factored as part of a dense front, over the factor's life.
    dense_columns: usize,
    /// During a refactor: the update matrices of its fronts so far, and the fronts' columns
    /// (`covered`: their contributions come from those).
    fronts: FrontUpdates,
    front_columns: Vec<u32>,
}

/// The variable whose pivot failed: `H` is not positive definite in its column.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct NotPositiveDefinite(pub usize);

impl BlockFactor {
    /// Room for `n` variables; new ones have dimension `dims[v]` (0: not in the system).
    pub fn grow(&mut self, dims: &[usize]) {
        let n = dims.len();
        let old = self.dim.len();
        self.dim.extend_from_slice(&dims[old..]);
        self.rank.resize(n, 0);
        self.columns.resize_with(n, Column::default);
        self.row_columns.resize_with(n, Vec::new);
        self.parent.resize(n, NONE);
        self.children.resize_with(n, Vec::new);
        self.changed.resize(n, false);
        self.covered.resize(n, false);
        self.kept_root.resize(n, NONE);
        self.slot.resize(n, NONE);
    }

    /// Columns factored in dense fronts so far (see `front`).
    pub fn dense_columns(&self) -> usize {
        self.dense_columns
    }

    /// Bytes of the kept subtrees' update matrices.
    pub fn kept_update_bytes(&self) -> usize {
        self.kept.bytes()
    }

    /// Bytes of the buffers dense fronts are built in, kept between refactors.
    pub fn front_scratch_bytes(&self) -> usize {
        self.fronts.scratch_bytes()
    }

    pub fn nnz(&self) -> usize {
        self.nnz
    }

    pub fn parent(&self, v: usize) -> Option<usize> {
        (self.parent[v] != NONE).then_some(self.parent[v] as usize)
    }

    /// The untouched columns with a block in a row of `affected` (marked in `in_affected`):
    /// the roots of the subtrees an update keeps, and any deeper column reaching that high.
    pub fn reaching(&self, affected: &[usize], in_affected: &[bool]) -> Vec<usize> {
        let mut seen: Vec<usize> = affected
            .iter()
            .flat_map(|&r| &self.row_columns[r])
            .map(|&(k, _)| k as usize)
            .filter(|&k| !in_affected[k])
            .collect();
        seen.sort_unstable();
        seen.dedup();
        seen
    }

    /// The rows of column `k` (variables).
    pub fn rows_of(&self, k: usize) -> impl Iterator<Item = usize> + '_ {
        self.columns[k].rows.iter().map(|&(u, _)| u as usize)
    }

    /// Eliminates the columns of `order` again, in that order, after every other column: drops
    /// their old values, gives them fresh ranks, and gathers `H`'s entries of column `r` with
    /// `assemble(r, rank, accumulator)` (which must add the blocks `(u, r)` for every `u` of
    /// higher rank that shares a factor with `r`, and the diagonal). Every ancestor of a
    /// variable in `order` must be in it; `reaching` is [`BlockFactor::reaching`] of it. On
    /// `Err` the factor is unusable (rebuild it).
    pub fn refactor(
        &mut self,
        order: &[usize],
        in_order: &[bool],
        reaching: &[usize],
        mut assemble: impl FnMut(usize, &[u64], &mut Accumulator),
    ) -> Result<(), NotPositiveDefinite> {
        // Forget the old columns (their rows are all in `order`: ancestors of affected columns).
        for &r in order {
            self.nnz -= self.column_nnz(r, &self.columns[r]);
            // Cleared, not dropped: the column is rebuilt into the same allocations.
            let old = &mut self.columns[r];
            old.diagonal.clear();
            old.rows.clear();
            old.blocks.clear();
            self.row_columns[r].retain(|&(k, _)| !in_order[k as usize]);
            self.children[r].retain(|&c| !in_order[c as usize]);
            self.roots.remove(&(r as u32));
            self.parent[r] = NONE;
        }
        for &r in order {
            self.rank[r] = self.next_rank;
            self.next_rank += 1;
            self.kept.forget(r);
        }
        let (members, mut kept_at) = self.prepare_kept_updates(reaching, in_order);
        let mut acc = std::mem::take(&mut self.accumulator);
        let result = self.eliminate(order, &mut acc, &mut assemble, &mut kept_at);
        self.accumulator = acc;
        for (_, k) in members {
            self.covered[k as usize] = false;
        }
        for k in self.front_columns.drain(..) {
            self.covered[k as usize] = false;
        }
        self.fronts.end_refactor(8 * self.nnz);
        self.kept.end_refactor(8 * self.nnz);
        result
    }

    /// Left-looking elimination of `order`, column by column, except where a run of columns
    /// forms one clique: that front is factored as one dense matrix (see `front`).
    fn eliminate<A: FnMut(usize, &[u64], &mut Accumulator)>(
        &mut self,
        order: &[usize],
        acc: &mut Accumulator,
        assemble: &mut A,
        kept_at: &mut KeptApplications,
    ) -> Result<(), NotPositiveDefinite> {
        let mut i = 0;
        while let Some(&r) = order.get(i) {
            self.gather(r, acc, assemble, kept_at);
            if let Some(width) = front::front_at(order, i, acc) {
                self.eliminate_front(&order[i..i + width], acc, assemble, kept_at)?;
                i += width;
                continue;
            }
            i += 1;
            if small_cholesky(&mut acc.diagonal, self.dim[r]).is_err() {
                acc.finish();
                return Err(NotPositiveDefinite(r));
            }
            self.scale_blocks(acc);
            self.store_column(r, acc);
        }
        Ok(())
    }

    /// Column `r` of `H` (by `assemble`) minus what every column eliminated before it
    /// contributes, into `acc`.
    fn gather<A: FnMut(usize, &[u64], &mut Accumulator)>(
        &mut self,
        r: usize,
        acc: &mut Accumulator,
        assemble: &mut A,
        kept_at: &mut KeptApplications,
    ) {
        acc.start(self.dim[r], self.dim.len());
        assemble(r, &self.rank, acc);
        self.subtract_updates(r, acc);
        let rank_r = self.rank[r];
        while let Some(&(rank, root, at)) = kept_at.list.get(kept_at.next) {
            if rank != rank_r {
                break;
            }
            let rank_of = &self.rank;
            let later = |u| rank_of[u] > rank_r;
            let (root, at) = (root as usize, at as usize);
            self.kept
                .subtract_from_column(root, at, &self.dim, acc, later);
            kept_at.next += 1;
        }
        self.fronts.subtract_due(rank_r, &self.dim, acc);
    }

    /// Stores the eliminated column `r` (in `acc`, then cleared): see
    /// [`BlockFactor::register_column`].
    fn store_column(&mut self, r: usize, acc: &mut Accumulator) {
        let column = &mut self.columns[r];
        column.diagonal.extend_from_slice(&acc.diagonal);
        column.rows.extend_from_slice(&acc.entries);
        column.blocks.extend_from_slice(&acc.buffer);
        acc.finish();
        self.register_column(r);
    }

    /// Column `r` has been eliminated and stored: its rows register it, and its parent is its
    /// lowest-ranked row.
    fn register_column(&mut self, r: usize) {
        let mut parent = NONE;
        for &(u, o) in &self.columns[r].rows {
            self.row_columns[u as usize].push((r as u32, o));
            if parent == NONE || self.rank[u as usize] < self.rank[parent as usize] {
                parent = u;
            }
        }
        self.nnz += self.column_nnz(r, &self.columns[r]);
        self.set_parent(r, parent);
    }

    /// Before the refactored part (fresh ranks) is eliminated: groups the kept columns
    /// `reaching` it by the root of their kept subtree, makes sure each group of two or more has
    /// its update matrix (computed now when it is not kept yet) and marks its columns
    /// `covered`. Returns the groups' members `(root, column)` and where the update matrices
    /// apply (each row of each root).
    fn prepare_kept_updates(
        &mut self,
        reaching: &[usize],
        in_order: &[bool],
    ) -> (Vec<(u32, u32)>, KeptApplications) {
        let mut members: Vec<(u32, u32)> = Vec::with_capacity(reaching.len());
        let mut visited: Vec<u32> = Vec::new();
        let mut path: Vec<u32> = Vec::new();
        for &k in reaching {
            let k = k as u32;
            self.covered[k as usize] = true;
            // Up the (old) tree to the last column before the refactored part.
            path.clear();
            let mut x = k;
            let root = loop {
                if self.kept_root[x as usize] != NONE {
                    break self.kept_root[x as usize];
                }
                path.push(x);
                let p = self.parent[x as usize];
                if p == NONE || in_order[p as usize] {
                    break x;
                }
                x = p;
            };
            for &v in &path {
                self.kept_root[v as usize] = root;
            }
            visited.extend_from_slice(&path);
            members.push((root, k));
        }
        for v in visited {
            self.kept_root[v as usize] = NONE;
        }
        members.sort_unstable();
        let mut applications = Vec::new();
        let mut kept_members = Vec::with_capacity(members.len());
        for group in members.chunk_by(|a, b| a.0 == b.0) {
            let root = group[0].0 as usize;
            if !self.kept.contains(root) {
                if group.len() < 2 {
                    self.covered[group[0].1 as usize] = false;
                    continue;
                }
                let rows: Vec<u32> = self.columns[root].rows.iter().map(|&(u, _)| u).collect();
                debug_assert!(rows.iter().all(|&u| in_order[u as usize]));
                let columns = &self.columns;
                let dim = &self.dim;
                let views = group.iter().map(|&(_, k)| ColumnView {
                    dim: dim[k as usize],
                    rows: &columns[k as usize].rows,
                    blocks: &columns[k as usize].blocks,
                });
                self.kept.compute(root, rows, views, dim, &mut self.slot);
            }
            kept_members.extend_from_slice(group);
            // A kept update's rows are its root's, in the same order (the root is not
            // refactored while its update is kept).
            applications.extend(
                self.columns[root]
                    .rows
                    .iter()
                    .enumerate()
                    .map(|(at, &(u, _))| (self.rank[u as usize], root as u32, at as u32)),
            );
        }
        applications.sort_unstable();
        let kept_at = KeptApplications {
            list: applications,
            next: 0,
        };
        (kept_members, kept_at)
    }

    /// `H`'s column `r` (in `acc`) minus `Σ_k L_{·k} L_rkᵀ` over the columns `k` reaching row
    /// `r`: where elimination spends its time, so compiled with AVX2 + FMA where the CPU has
    /// them (see `solver::simd`).
    fn subtract_updates(&self, r: usize, acc: &mut Accumulator) {
        if crate::solver::simd::has_wide_vectors() {
            // SAFETY: the CPU has the features `subtract_updates_wide` is compiled for.
            unsafe { self.subtract_updates_wide(r, acc) }
        } else {
            self.subtract_updates_with::<false>(r, acc)
        }
    }

    #[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma"))]
    fn subtract_updates_wide(&self, r: usize, acc: &mut Accumulator) {
        self.subtract_updates_with::<true>(r, acc)
    }

    #[inline(always)]
    fn subtract_updates_with<const FUSED: bool>(&self, r: usize, acc: &mut Accumulator) {
        let d = self.dim[r];
        let rank_r = self.rank[r];
        for &(k, at) in &self.row_columns[r] {
            if self.covered[k as usize] {
                // In a kept subtree whose update matrix carries it.
                continue;
            }
            let column = &self.columns[k as usize];
            let dk = self.dim[k as usize];
            let at = at as usize;
            let l_rk = &column.blocks[at..at + d * dk];
            dense::sub_mul_transpose::<FUSED>(&mut acc.diagonal, l_rk, l_rk, d, d, dk);
            for &(u, o) in &column.rows {
                let u = u as usize;
                if self.rank[u] > rank_r {
                    let du = self.dim[u];
                    let l_uk = &column.blocks[o as usize..o as usize + du * dk];
                    dense::sub_mul_transpose::<FUSED>(acc.block_mut(u, du), l_uk, l_rk, du, d, dk);
                }
            }
        }
    }

    /// `L_ur = A'_ur L_rr⁻ᵀ` for every block of the column (its diagonal already factored).
    fn scale_blocks(&self, acc: &mut Accumulator) {
        if crate::solver::simd::has_wide_vectors() {
            // SAFETY: the CPU has the features `scale_blocks_wide` is compiled for.
            unsafe { self.scale_blocks_wide(acc) }
        } else {
            self.scale_blocks_with::<false>(acc)
        }
    }

    #[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma"))]
    fn scale_blocks_wide(&self, acc: &mut Accumulator) {
        self.scale_blocks_with::<true>(acc)
    }

    #[inline(always)]
    fn scale_blocks_with<const FUSED: bool>(&self, acc: &mut Accumulator) {
        let d = acc.dim;
        dense::negated_lower_inverse(&acc.diagonal, d, &mut acc.inverse);
        for &(u, o) in &acc.entries {
            let du = self.dim[u as usize];
            let o = o as usize;
            let block = &mut acc.buffer[o..o + du * d];
            dense::times_inverse_transpose::<FUSED>(block, &acc.inverse, du, d, &mut acc.scratch);
        }
    }

    /// Sets each column of `columns` to its lowest-ranked row as parent again: after
    /// [`BlockFactor::refactor`], the untouched columns reaching the refactored part keep their
    /// values, but that row may have moved; after a rank update, fill may have added one.
    pub fn reparent(&mut self, reaching: &[usize]) {
        for &u in reaching {
            let parent = self.columns[u]
                .rows
                .iter()
                .map(|&(p, _)| p)
                .min_by_key(|&p| self.rank[p as usize])
                .unwrap_or(NONE);
            if parent != self.parent[u] {
                if self.parent[u] != NONE {
                    let old = self.parent[u] as usize;
                    self.children[old].retain(|&c| c as usize != u);
                } else {
                    self.roots.remove(&(u as u32));
                }
                self.parent[u] = NONE;
                self.set_parent(u, parent);
            }
        }
    }

    fn set_parent(&mut self, v: usize, parent: u32) {
        self.parent[v] = parent;
        if parent == NONE {
            self.roots.insert(v as u32);
        } else {
            self.children[parent as usize].push(v as u32);
        }
    }

    /// What eliminating column `v` as it stands costs: `d·s·(s + d)` for `s` scalar rows below
    /// its `d`-wide diagonal block (its panel solve and its update of the later columns).
    pub fn elimination_flops(&self, v: usize) -> f64 {
        let (d, s) = (self.dim[v], self.scalar_rows(v));
        (d * s * (s + d)) as f64
    }

    /// Scalar rows of column `v` below its diagonal block.
    pub fn scalar_rows(&self, v: usize) -> usize {
        self.columns[v]
            .blocks
            .len()
            .checked_div(self.dim[v])
            .unwrap_or(0)
    }

    fn column_nnz(&self, v: usize, column: &Column) -> usize {
        let d = self.dim[v];
        if column.diagonal.is_empty() {
            return 0;
        }
        d * (d + 1) / 2 + column.blocks.len()
    }
}

#[path = "front.rs"]
mod front;

#[path = "rank_update.rs"]
mod rank_update;
pub use rank_update::{rank_update_flops, UpdateRows};

#[path = "block_solve.rs"]
mod block_solve;
pub use block_solve::Solution;

#[cfg(test)]
#[path = "block_factor_tests.rs"]
mod tests;
