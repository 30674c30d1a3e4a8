//! One solve with the last factorisation: the reduced right-hand side b_r − W V⁻¹ b_e, S's
//! solve for Δr, then back-substitution Δe = V⁻¹ (b_e − Wᵀ Δr) block by block.

use std::ops::Range;

use super::super::simd::has_wide_vectors;
use super::{kernel_of, SchurSolver, CAMERA};

impl SchurSolver {
    /// Solves with the last successful [`SchurSolver::factorize`]; `rhs` in the full layout.
    pub fn solve_in_place(&mut self, rhs: &mut [f64]) {
        let n = self.reduced.n;
        let base = self.eliminated_rows;
        self.rhs.copy_from_slice(&rhs[base..base + n]);
        self.reduce_parts(rhs, reduce_rhs);
        self.backend.solve_in_place(&self.s_values, &mut self.rhs);
        rhs[base..base + n].copy_from_slice(&self.rhs);
        let (head, tail) = rhs.split_at_mut(base);
        self.back_substitute_parts(head, tail, back_substitute);
    }

    /// `out −= Σ_k Y_k b_e` for eliminated block `e` (dimensions as in the elimination).
    #[inline(always)]
    fn reduce_one<const D: usize, const K: usize>(&self, e: usize, rhs: &[f64], out: &mut [f64]) {
        let d = if D > 0 { D } else { self.dim[e] };
        let o = self.offset[e];
        let be = &rhs[o..o + d];
        for nb in &self.neighbours[self.neighbour_start[e]..self.neighbour_start[e + 1]] {
            let dk = if K > 0 { K } else { self.reduced.dim[nb.block] };
            let ok = self.reduced.offset[nb.block];
            let y = &self.y_values[nb.y_offset..nb.y_offset + dk * d];
            let out = &mut out[ok..ok + dk];
            for t in 0..d {
                let b = be[t];
                for (x, yr) in out.iter_mut().zip(&y[t * dk..(t + 1) * dk]) {
                    *x -= yr * b;
                }
            }
        }
    }

    /// Δe = V⁻¹ b_e − Σ_k Y_kᵀ Δr_k for eliminated block `e`; `head` holds b_e on entry, from
    /// row `first` on.
    #[inline(always)]
    fn back_substitute_one<const D: usize, const K: usize>(
        &self,
        e: usize,
        head: &mut [f64],
        first: usize,
        tail: &[f64],
    ) {
        let d = if D > 0 { D } else { self.dim[e] };
        let o = self.offset[e] - first;
        let v = &self.v_inverse[self.v_start[e]..self.v_start[e + 1]];
        let xe = &mut head[o..o + d];
        let mut be = [0.0; 16];
        be[..d].copy_from_slice(xe);
        for (i, x) in xe.iter_mut().enumerate() {
            *x = (0..d).map(|j| v[i * d + j] * be[j]).sum();
        }
        for nb in &self.neighbours[self.neighbour_start[e]..self.neighbour_start[e + 1]] {
            let dk = if K > 0 { K } else { self.reduced.dim[nb.block] };
            let ok = self.reduced.offset[nb.block];
            let y = &self.y_values[nb.y_offset..nb.y_offset + dk * d];
            let xr = &tail[ok..ok + dk];
            for (t, x) in xe.iter_mut().enumerate() {
                *x -= y[t * dk..(t + 1) * dk]
                    .iter()
                    .zip(xr)
                    .map(|(a, b)| a * b)
                    .sum::<f64>();
            }
        }
    }
}

#[inline(always)]
fn reduce_rhs_with(solver: &SchurSolver, blocks: Range<usize>, rhs: &[f64], out: &mut [f64]) {
    for e in blocks {
        match kernel_of(solver, e) {
            (3, true) => solver.reduce_one::<3, CAMERA>(e, rhs, out),
            _ => solver.reduce_one::<0, 0>(e, rhs, out),
        }
    }
}

#[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma"))]
fn reduce_rhs_wide(solver: &SchurSolver, blocks: Range<usize>, rhs: &[f64], out: &mut [f64]) {
    reduce_rhs_with(solver, blocks, rhs, out)
}

/// The reduced right-hand side's part of eliminated blocks `blocks`, subtracted from `out`.
fn reduce_rhs(solver: &SchurSolver, blocks: Range<usize>, rhs: &[f64], out: &mut [f64]) {
    if has_wide_vectors() {
        // SAFETY: the CPU has the features `reduce_rhs_wide` is compiled for.
        unsafe { reduce_rhs_wide(solver, blocks, rhs, out) }
    } else {
        reduce_rhs_with(solver, blocks, rhs, out)
    }
}

#[inline(always)]
fn back_substitute_with(
    solver: &SchurSolver,
    blocks: Range<usize>,
    head: &mut [f64],
    first: usize,
    tail: &[f64],
) {
    for e in blocks {
        match kernel_of(solver, e) {
            (3, true) => solver.back_substitute_one::<3, CAMERA>(e, head, first, tail),
            _ => solver.back_substitute_one::<0, 0>(e, head, first, tail),
        }
    }
}

#[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma"))]
fn back_substitute_wide(
    solver: &SchurSolver,
    blocks: Range<usize>,
    head: &mut [f64],
    first: usize,
    tail: &[f64],
) {
    back_substitute_with(solver, blocks, head, first, tail)
}

/// Δe of eliminated blocks `blocks` into `head` (their rows, from row `first` on).
fn back_substitute(
    solver: &SchurSolver,
    blocks: Range<usize>,
    head: &mut [f64],
    first: usize,
    tail: &[f64],
) {
    if has_wide_vectors() {
        // SAFETY: the CPU has the features `back_substitute_wide` is compiled for.
        unsafe { back_substitute_wide(solver, blocks, head, first, tail) }
    } else {
        back_substitute_with(solver, blocks, head, first, tail)
    }
}
