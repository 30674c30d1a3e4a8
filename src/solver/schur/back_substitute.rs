//! One solve with the last factorisation: the reduced right-hand side b_r − W V⁻¹ b_e, S's
//! solve for Δr, then back-substitution Δe = V⁻¹ (b_e − Wᵀ Δr) block by block.

use super::super::simd::has_wide_vectors;
use super::{kernel_of, SchurSolver, CAMERA};

impl SchurSolver {
    /// Solves with the last successful [`SchurSolver::factorize`]; `rhs` in the full layout.
    /// Solves with the last successful [`SchurSolver::factorize`]; `rhs` in the full layout.
    pub fn solve_in_place(&mut self, rhs: &mut [f64]) {
        let n = self.reduced.n;
        let base = self.eliminated_rows;
        self.rhs.copy_from_slice(&rhs[base..base + n]);
        if has_wide_vectors() {
            // SAFETY: the CPU has the features `reduce_rhs_wide` is compiled for.
            unsafe { reduce_rhs_wide(self, rhs) }
        } else {
            reduce_rhs(self, rhs)
        }
        self.backend.solve_in_place(&self.s_values, &mut self.rhs);
        rhs[base..base + n].copy_from_slice(&self.rhs);
        if has_wide_vectors() {
            // SAFETY: as above.
            unsafe { back_substitute_wide(self, rhs) }
        } else {
            back_substitute(self, rhs)
        }
    }

    /// rhs_r −= Σ_k Y_k b_e for eliminated block `e` (dimensions as in [`Self::eliminate`]).
    #[inline(always)]
    fn reduce_one<const D: usize, const K: usize>(&mut self, e: usize, rhs: &[f64]) {
        let d = if D > 0 { D } else { self.dim[e] };
        let o = self.offset[e];
        let be = &rhs[o..o + d];
        for nb in &self.neighbours[self.neighbour_start[e]..self.neighbour_start[e + 1]] {
            let dk = if K > 0 { K } else { self.reduced.dim[nb.block] };
            let ok = self.reduced.offset[nb.block];
            let y = &self.y_values[nb.y_offset..nb.y_offset + dk * d];
            let out = &mut self.rhs[ok..ok + dk];
            for t in 0..d {
                let b = be[t];
                for (x, yr) in out.iter_mut().zip(&y[t * dk..(t + 1) * dk]) {
                    *x -= yr * b;
                }
            }
        }
    }

    /// Δe = V⁻¹ b_e − Σ_k Y_kᵀ Δr_k for eliminated block `e`; `head` holds b_e on entry.
    #[inline(always)]
    fn back_substitute_one<const D: usize, const K: usize>(
        &self,
        e: usize,
        head: &mut [f64],
        tail: &[f64],
    ) {
        let d = if D > 0 { D } else { self.dim[e] };
        let o = self.offset[e];
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
fn reduce_rhs(solver: &mut SchurSolver, rhs: &[f64]) {
    for e in 0..solver.eliminated {
        match kernel_of(solver, e) {
            (3, true) => solver.reduce_one::<3, CAMERA>(e, rhs),
            _ => solver.reduce_one::<0, 0>(e, rhs),
        }
    }
}

#[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma"))]
fn reduce_rhs_wide(solver: &mut SchurSolver, rhs: &[f64]) {
    reduce_rhs(solver, rhs)
}

#[inline(always)]
fn back_substitute(solver: &SchurSolver, rhs: &mut [f64]) {
    let (head, tail) = rhs.split_at_mut(solver.eliminated_rows);
    for e in 0..solver.eliminated {
        match kernel_of(solver, e) {
            (3, true) => solver.back_substitute_one::<3, CAMERA>(e, head, tail),
            _ => solver.back_substitute_one::<0, 0>(e, head, tail),
        }
    }
}

#[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma"))]
fn back_substitute_wide(solver: &SchurSolver, rhs: &mut [f64]) {
    back_substitute(solver, rhs)
}
