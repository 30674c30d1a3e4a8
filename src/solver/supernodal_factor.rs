//! Numeric `A = L Lᵀ` on a supernodal structure ([`Supernodes`]), with plain loops for the
//! small supernodes of pose graphs and faer's dense kernels for the large ones.
//!
//! Left-looking, as faer's own: supernode by supernode, each
//! 1. gathers A's lower columns into its dense block (`L_top` c × c over `L_bot`, one row per
//!    index in its pattern, column-major, as [`supernodal_solve`](super::supernodal_solve)
//!    reads it);
//! 2. subtracts `L_d[rows ≥ s] L_d[rows of s]ᵀ` of every earlier supernode d whose pattern
//!    reaches its columns (the lists are built once, at analysis);
//! 3. factorises itself: `L_top ← chol(L_top)`, `L_bot ← L_bot L_top⁻ᵀ`.
//!
//! faer calls its general matrix-multiply, Cholesky and triangular-solve routines for every
//! supernode and every update; on a 2D pose graph (supernodes of 3–16 columns) their dispatch
//! costs more than the arithmetic. Here an update below [`LOOPS_UP_TO`] multiply-adds, and a
//! supernode of at most [`LOOPS_UP_TO_COLUMNS`] columns, run as column-contiguous loops; larger
//! ones (the dense top of a 3D graph) still go to faer's blocked kernels.

use dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::{
    cholesky_in_place, cholesky_in_place_scratch, LltError, LltRegularization,
};
use faer::linalg::matmul::matmul;
use faer::linalg::triangular_solve::solve_lower_triangular_in_place;
use faer::reborrow::{Reborrow, ReborrowMut};
use faer::sparse::SparseColMatRef;
use faer::{Accum, MatMut, MatRef, Par, Spec};

use super::cholesky::NotPositiveDefinite;
use super::simd::has_wide_vectors;
use super::supernodes::Supernodes;

/// Updates of at most this many multiply-adds run as loops, larger ones in faer's matmul.
const LOOPS_UP_TO: usize = 4096;
/// Supernodes of at most this many columns factorise themselves in loops.
const LOOPS_UP_TO_COLUMNS: usize = 24;

/// What the numeric factorisation needs besides the supernodal structure, built once.
pub(super) struct SupernodalPlan {
    /// For supernode s, `descendants[starts[s]..starts[s + 1]]`: the earlier supernodes whose
    /// pattern has a row among s's columns (each updates s once).
    starts: Vec<usize>,
    descendants: Vec<usize>,
    /// Per scalar row: its row in the current supernode's block (scratch, set for the current
    /// supernode's pattern; the other entries are stale and never read).
    local: Vec<usize>,
    /// Per supernode: where in its pattern the rows of the supernodes not yet factorised begin
    /// (each pattern is consumed in order as the supernodes it updates come up).
    cursor: Vec<usize>,
    /// One update's product, rows ≥ s by s's rows it touches (scratch).
    product: Vec<f64>,
    /// faer's dense Cholesky's workspace for the largest supernode.
    dense_mem: MemBuffer,
}

impl SupernodalPlan {
    pub(super) fn new(symbolic: &Supernodes) -> Self {
        let n = symbolic.n();
        let supernodes = symbolic.count();
        let mut supernode_of = vec![0; n];
        let mut widest = 0;
        for s in 0..supernodes {
            let columns = symbolic.columns(s);
            widest = widest.max(columns.len());
            supernode_of[columns].fill(s);
        }
        // Each descendant's pattern is sorted, so the supernodes it updates come in order and
        // repeats are adjacent. Two passes: count per supernode, then fill in ascending d.
        let each_update = |visit: &mut dyn FnMut(usize, usize)| {
            for d in 0..supernodes {
                let mut last = usize::MAX;
                for &row in symbolic.pattern(d) {
                    let s = supernode_of[row];
                    if s != last {
                        visit(s, d);
                        last = s;
                    }
                }
            }
        };
        let mut starts = vec![0; supernodes + 1];
        each_update(&mut |s, _| starts[s + 1] += 1);
        for s in 0..supernodes {
            starts[s + 1] += starts[s];
        }
        let mut next = starts.clone();
        let mut descendants = vec![0; starts[supernodes]];
        each_update(&mut |s, d| {
            descendants[next[s]] = d;
            next[s] += 1;
        });
        Self {
            starts,
            descendants,
            local: vec![0; n],
            cursor: vec![0; supernodes],
            product: Vec::new(),
            dense_mem: MemBuffer::new(cholesky_in_place_scratch::<f64>(
                widest,
                Par::Seq,
                Spec::default(),
            )),
        }
    }

    /// Bytes held (for the memory estimate).
    pub(super) fn bytes(&self) -> usize {
        let indices = self.starts.len() + self.descendants.len() + self.local.len();
        8 * (indices + self.cursor.len() + self.product.len())
    }

    /// Factorises `a` (lower triangle, in elimination order) into `l`, laid out as `symbolic`.
    /// The loops are compiled with AVX2 + FMA where the CPU has them (see `solver::simd`).
    pub(super) fn factorize(
        &mut self,
        symbolic: &Supernodes,
        a: SparseColMatRef<'_, usize, f64>,
        l: &mut [f64],
    ) -> Result<(), NotPositiveDefinite> {
        if has_wide_vectors() {
            // SAFETY: the CPU has the features `factorize_wide` is compiled for.
            unsafe { self.factorize_wide(symbolic, a, l) }
        } else {
            self.factorize_with::<false>(symbolic, a, l)
        }
    }

    #[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma"))]
    fn factorize_wide(
        &mut self,
        symbolic: &Supernodes,
        a: SparseColMatRef<'_, usize, f64>,
        l: &mut [f64],
    ) -> Result<(), NotPositiveDefinite> {
        self.factorize_with::<true>(symbolic, a, l)
    }

    /// `FUSED`: the loops' multiply-adds fused (for the variant compiled with FMA).
    #[inline(always)]
    fn factorize_with<const FUSED: bool>(
        &mut self,
        symbolic: &Supernodes,
        a: SparseColMatRef<'_, usize, f64>,
        l: &mut [f64],
    ) -> Result<(), NotPositiveDefinite> {
        let offsets = symbolic.value_ptr();
        self.cursor.fill(0);
        for s in 0..symbolic.count() {
            let begin = symbolic.columns(s).start;
            let columns = symbolic.columns(s).len();
            let pattern = symbolic.pattern(s);
            let rows = columns + pattern.len();
            for (k, &row) in pattern.iter().enumerate() {
                self.local[row] = columns + k;
            }
            let (earlier, rest) = l.split_at_mut(offsets[s]);
            let block = &mut rest[..offsets[s + 1] - offsets[s]];
            block.fill(0.0);
            for j in 0..columns {
                let column = &mut block[j * rows..(j + 1) * rows];
                let entries = a.row_idx_of_col(begin + j).zip(a.val_of_col(begin + j));
                for (row, &value) in entries.filter(|&(row, _)| row >= begin + j) {
                    column[self.local_row(row, begin, columns)] = value;
                }
            }
            for i in self.starts[s]..self.starts[s + 1] {
                let d = self.descendants[i];
                let d_block = &earlier[offsets[d]..offsets[d + 1]];
                self.subtract_update::<FUSED>(symbolic, d, d_block, block, begin, columns);
            }
            factorize_block::<FUSED>(block, columns, rows, &mut self.dense_mem)
                .map_err(|local| NotPositiveDefinite { row: begin + local })?;
        }
        Ok(())
    }

    /// Row of scalar `row` in the block of the supernode starting at `begin`.
    #[inline(always)]
    fn local_row(&self, row: usize, begin: usize, columns: usize) -> usize {
        if row < begin + columns {
            row - begin
        } else {
            self.local[row]
        }
    }

    /// `block −= L_d[rows ≥ begin] L_d[rows in s]ᵀ` (lower part), scattered by row.
    #[inline(always)]
    fn subtract_update<const FUSED: bool>(
        &mut self,
        symbolic: &Supernodes,
        d: usize,
        d_block: &[f64],
        block: &mut [f64],
        begin: usize,
        columns: usize,
    ) {
        let d_columns = symbolic.columns(d).len();
        let d_pattern = symbolic.pattern(d);
        let d_rows = d_columns + d_pattern.len();
        let first = self.cursor[d];
        let touched = d_pattern[first..]
            .iter()
            .take_while(|&&row| row < begin + columns)
            .count();
        self.cursor[d] = first + touched;
        let below = &d_pattern[first..];
        let m = below.len();
        let rows = block.len() / columns;
        if m * touched * d_columns <= LOOPS_UP_TO {
            // Four rows of the product at a time, summed over d's columns in registers, then
            // subtracted where they belong.
            let below_columns =
                |k: usize| &d_block[k * d_rows + d_columns + first..(k + 1) * d_rows];
            for jj in 0..touched {
                let target = (below[jj] - begin) * rows;
                let mut i = jj;
                while i + 4 <= m {
                    let mut sums = [0.0; 4];
                    for k in 0..d_columns {
                        let column = below_columns(k);
                        add_scaled_4::<FUSED>(&mut sums, &column[i..i + 4], column[jj]);
                    }
                    for lane in 0..4 {
                        block[target + self.local_row(below[i + lane], begin, columns)] -=
                            sums[lane];
                    }
                    i += 4;
                }
                for i in i..m {
                    let sum: f64 = (0..d_columns)
                        .map(|k| below_columns(k)[i] * below_columns(k)[jj])
                        .sum();
                    block[target + self.local_row(below[i], begin, columns)] -= sum;
                }
            }
            return;
        }
        self.product.clear();
        self.product.resize(m * touched, 0.0);
        let l_d = MatRef::from_column_major_slice(d_block, d_rows, d_columns)
            .subrows(d_columns + first, m);
        let product = MatMut::from_column_major_slice_mut(&mut self.product, m, touched);
        matmul(
            product,
            Accum::Replace,
            l_d,
            l_d.subrows(0, touched).transpose(),
            1.0,
            Par::Seq,
        );
        for jj in 0..touched {
            let target = &mut block[(below[jj] - begin) * rows..][..rows];
            for (&row, p) in below[jj..]
                .iter()
                .zip(&self.product[jj * m + jj..(jj + 1) * m])
            {
                target[self.local_row(row, begin, columns)] -= p;
            }
        }
    }
}

/// `L_top ← chol(L_top)`, `L_bot ← L_bot L_top⁻ᵀ` on a supernode's block; `Err` with the
/// column whose pivot was not positive.
#[inline(always)]
fn factorize_block<const FUSED: bool>(
    block: &mut [f64],
    columns: usize,
    rows: usize,
    dense_mem: &mut MemBuffer,
) -> Result<(), usize> {
    if columns > LOOPS_UP_TO_COLUMNS {
        let all = MatMut::from_column_major_slice_mut(block, rows, columns);
        let (mut top, bottom) = all.split_at_row_mut(columns);
        cholesky_in_place(
            top.rb_mut(),
            LltRegularization::default(),
            Par::Seq,
            MemStack::new(dense_mem),
            Spec::default(),
        )
        .map_err(|LltError::NonPositivePivot { index }| index)?;
        solve_lower_triangular_in_place(top.rb(), bottom.transpose_mut(), Par::Seq);
        return Ok(());
    }
    // Left-looking over the whole panel: column k, down to its last row, less its products
    // with the columns before it (summed four rows at a time in registers), then scaled by its
    // pivot; scaling below the pivot also solves `L_bot`'s rows against `L_top`.
    for k in 0..columns {
        let (done, rest) = block.split_at_mut(k * rows);
        let column = &mut rest[..rows];
        let mut i = k;
        while i + 4 <= rows {
            let mut sums = [0.0; 4];
            for j in 0..k {
                let earlier = &done[j * rows..(j + 1) * rows];
                add_scaled_4::<FUSED>(&mut sums, &earlier[i..i + 4], earlier[k]);
            }
            for (value, sum) in column[i..i + 4].iter_mut().zip(sums) {
                *value -= sum;
            }
            i += 4;
        }
        for i in i..rows {
            let sum: f64 = (0..k)
                .map(|j| done[j * rows + i] * done[j * rows + k])
                .sum();
            column[i] -= sum;
        }
        let pivot = column[k];
        if pivot.is_nan() || pivot <= 0.0 {
            return Err(k);
        }
        let pivot = pivot.sqrt();
        column[k] = pivot;
        let inverse = pivot.recip();
        for l_ik in &mut column[k + 1..] {
            *l_ik *= inverse;
        }
    }
    Ok(())
}

/// `sums += factor · rows` over four lanes (the compiler keeps them in one vector register),
/// fused where `FUSED`.
#[inline(always)]
fn add_scaled_4<const FUSED: bool>(sums: &mut [f64; 4], rows: &[f64], factor: f64) {
    for (sum, &row) in sums.iter_mut().zip(&rows[..4]) {
        *sum = if FUSED {
            row.mul_add(factor, *sum)
        } else {
            *sum + row * factor
        };
    }
}
