//! One solve with the last factorisation: the reduced right-hand side b_r − W V⁻¹ b_e, S's
//! solve for Δr, then back-substitution Δe = V⁻¹ (b_e − Wᵀ Δr) block by block, both reading W
//! from H (Y = W V⁻¹ is not kept: it would hold as much memory as W itself).

use std::ops::Range;

use super::super::simd::has_wide_vectors;
use super::super::structure::BlockPattern;
use super::threads::H;
use super::{kernel_of, SchurSolver, CAMERA};

impl SchurSolver {
    /// Solves with the last successful [`SchurSolver::factorize`]; `rhs` in the full layout.
    /// `full` and `values` are the H that factorisation eliminated (its W blocks are read
    /// again here; the shift only touched the diagonal).
    pub fn solve_in_place(&mut self, full: &BlockPattern, values: &[f64], rhs: &mut [f64]) {
        let n = self.reduced.n;
        let base = self.blocks.rows;
        self.rhs.copy_from_slice(&rhs[base..base + n]);
        self.reduce_parts((full, values), rhs, reduce_rhs);
        self.backend.solve_in_place(&self.s_values, &mut self.rhs);
        rhs[base..base + n].copy_from_slice(&self.rhs);
        let (head, tail) = rhs.split_at_mut(base);
        self.back_substitute_parts((full, values), head, tail, back_substitute);
    }

    /// `out −= Σ_k Y_k b_e = Σ_k W_k (V⁻¹ b_e)` for eliminated block `e` (dimensions as in the
    /// elimination).
    #[inline(always)]
    fn reduce_one<const D: usize, const K: usize>(
        &self,
        (full, values): H<'_>,
        e: usize,
        rhs: &[f64],
        out: &mut [f64],
    ) {
        let d = if D > 0 { D } else { self.blocks.dim[e] };
        let o = self.blocks.offset[e];
        let v = &self.v_inverse[self.blocks.v_range(e)];
        let mut t = [0.0; 16];
        for (i, ti) in t[..d].iter_mut().enumerate() {
            *ti = (0..d).map(|j| v[i * d + j] * rhs[o + j]).sum();
        }
        for nb in self.blocks.neighbours_of(e) {
            let dk = if K > 0 { K } else { self.reduced.dim[nb.block] };
            let ok = self.reduced.offset[nb.block];
            let out = &mut out[ok..ok + dk];
            for (s, &ts) in t[..d].iter().enumerate() {
                // Column s of W_k: contiguous in H.
                let start = full.value_index(nb.w_pair, false, 0, s);
                for (x, w) in out.iter_mut().zip(&values[start..start + dk]) {
                    *x -= w * ts;
                }
            }
        }
    }

    /// Δe = V⁻¹ (b_e − Σ_k W_kᵀ Δr_k) for eliminated block `e`; `head` (its rows from row
    /// `first` on) holds b_e on entry.
    #[inline(always)]
    fn back_substitute_one<const D: usize, const K: usize>(
        &self,
        (full, values): H<'_>,
        e: usize,
        (head, first): (&mut [f64], usize),
        tail: &[f64],
    ) {
        let d = if D > 0 { D } else { self.blocks.dim[e] };
        let o = self.blocks.offset[e] - first;
        let v = &self.v_inverse[self.blocks.v_range(e)];
        let xe = &mut head[o..o + d];
        let mut be = [0.0; 16];
        be[..d].copy_from_slice(xe);
        for nb in self.blocks.neighbours_of(e) {
            let dk = if K > 0 { K } else { self.reduced.dim[nb.block] };
            let ok = self.reduced.offset[nb.block];
            let xr = &tail[ok..ok + dk];
            for (s, b) in be[..d].iter_mut().enumerate() {
                let start = full.value_index(nb.w_pair, false, 0, s);
                *b -= values[start..start + dk]
                    .iter()
                    .zip(xr)
                    .map(|(w, x)| w * x)
                    .sum::<f64>();
            }
        }
        for (i, x) in xe.iter_mut().enumerate() {
            *x = (0..d).map(|j| v[i * d + j] * be[j]).sum();
        }
    }
}

#[inline(always)]
fn reduce_rhs_with(
    solver: &SchurSolver,
    h: H<'_>,
    blocks: Range<usize>,
    rhs: &[f64],
    out: &mut [f64],
) {
    for e in blocks {
        match kernel_of(solver, e) {
            (3, true) => solver.reduce_one::<3, CAMERA>(h, e, rhs, out),
            _ => solver.reduce_one::<0, 0>(h, e, rhs, out),
        }
    }
}

#[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma"))]
fn reduce_rhs_wide(
    solver: &SchurSolver,
    h: H<'_>,
    blocks: Range<usize>,
    rhs: &[f64],
    out: &mut [f64],
) {
    reduce_rhs_with(solver, h, blocks, rhs, out)
}

/// The reduced right-hand side's part of eliminated blocks `blocks`, subtracted from `out`.
fn reduce_rhs(solver: &SchurSolver, h: H<'_>, blocks: Range<usize>, rhs: &[f64], out: &mut [f64]) {
    if has_wide_vectors() {
        // SAFETY: the CPU has the features `reduce_rhs_wide` is compiled for.
        unsafe { reduce_rhs_wide(solver, h, blocks, rhs, out) }
    } else {
        reduce_rhs_with(solver, h, blocks, rhs, out)
    }
}

#[inline(always)]
fn back_substitute_with(
    solver: &SchurSolver,
    h: H<'_>,
    blocks: Range<usize>,
    (head, first): (&mut [f64], usize),
    tail: &[f64],
) {
    for e in blocks {
        let rows = (&mut *head, first);
        match kernel_of(solver, e) {
            (3, true) => solver.back_substitute_one::<3, CAMERA>(h, e, rows, tail),
            _ => solver.back_substitute_one::<0, 0>(h, e, rows, tail),
        }
    }
}

#[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma"))]
fn back_substitute_wide(
    solver: &SchurSolver,
    h: H<'_>,
    blocks: Range<usize>,
    rows: (&mut [f64], usize),
    tail: &[f64],
) {
    back_substitute_with(solver, h, blocks, rows, tail)
}

/// Δe of eliminated blocks `blocks` into their rows (a slice from the given row on).
fn back_substitute(
    solver: &SchurSolver,
    h: H<'_>,
    blocks: Range<usize>,
    rows: (&mut [f64], usize),
    tail: &[f64],
) {
    if has_wide_vectors() {
        // SAFETY: the CPU has the features `back_substitute_wide` is compiled for.
        unsafe { back_substitute_wide(solver, h, blocks, rows, tail) }
    } else {
        back_substitute_with(solver, h, blocks, rows, tail)
    }
}
