//! `L Lᵀ x = b` on a supernodal factor ([`Supernodes`]), with plain loops instead of faer's
//! dense kernels.
//!
//! faer solves supernode by supernode with its general triangular-solve and matrix-multiply
//! routines, whose dispatch costs more than the arithmetic on the few columns a pose graph's
//! supernode has (3–16): on input_INTEL_g2o its supernodal solve took 148 µs where its
//! simplicial solve of the same system took 47 µs. Here each supernode is
//!
//! ```text
//!     ⎡ L_top ⎤   c × c lower triangle (the supernode's own columns)
//!     ⎣ L_bot ⎦   one row per index in the supernode's pattern (rows below it)
//! ```
//!
//! stored column-major at `col_ptr_for_val[s]`. Forward: `x_top ← L_top⁻¹ x_top`, then
//! `x[pattern] −= L_bot x_top`. Backward, in reverse order: `x_top −= L_botᵀ x[pattern]`, then
//! `x_top ← L_top⁻ᵀ x_top`. Every inner loop runs down a contiguous column, so it vectorises.

use super::simd::has_wide_vectors;
use super::supernodes::Supernodes;
use super::vector::dot_interleaved as dot;

/// Solves `L Lᵀ x = b` in place (`x` holds `b` on entry); `below` is scratch (one supernode's
/// pattern). Compiled with AVX2 + FMA where the CPU has them (see `solver::simd`).
pub(super) fn solve_in_place(
    symbolic: &Supernodes,
    values: &[f64],
    x: &mut [f64],
    below: &mut Vec<f64>,
) {
    if has_wide_vectors() {
        // SAFETY: the CPU has the features `solve_in_place_wide` is compiled for.
        unsafe { solve_in_place_wide(symbolic, values, x, below) }
    } else {
        solve_in_place_with(symbolic, values, x, below)
    }
}

#[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma"))]
fn solve_in_place_wide(symbolic: &Supernodes, values: &[f64], x: &mut [f64], below: &mut Vec<f64>) {
    solve_in_place_with(symbolic, values, x, below)
}

#[inline(always)]
fn solve_in_place_with(symbolic: &Supernodes, values: &[f64], x: &mut [f64], below: &mut Vec<f64>) {
    let supernodes = symbolic.count();
    for s in 0..supernodes {
        let (begin, l, pattern) = supernode(symbolic, values, s);
        let columns = symbolic.columns(s).len();
        let rows = columns + pattern.len();
        below.clear();
        below.resize(pattern.len(), 0.0);
        for j in 0..columns {
            let column = &l[j * rows..(j + 1) * rows];
            let xj = x[begin + j] / column[j];
            x[begin + j] = xj;
            for (x_i, l_ij) in x[begin + j + 1..begin + columns]
                .iter_mut()
                .zip(&column[j + 1..columns])
            {
                *x_i -= l_ij * xj;
            }
            for (b, l_kj) in below.iter_mut().zip(&column[columns..]) {
                *b += l_kj * xj;
            }
        }
        for (&row, b) in pattern.iter().zip(below.iter()) {
            x[row] -= b;
        }
    }
    for s in (0..supernodes).rev() {
        let (begin, l, pattern) = supernode(symbolic, values, s);
        let columns = symbolic.columns(s).len();
        let rows = columns + pattern.len();
        below.clear();
        below.extend(pattern.iter().map(|&row| x[row]));
        for j in (0..columns).rev() {
            let column = &l[j * rows..(j + 1) * rows];
            let from_below = dot(below, &column[columns..]);
            let from_top = dot(&x[begin + j + 1..begin + columns], &column[j + 1..columns]);
            x[begin + j] = (x[begin + j] - from_below - from_top) / column[j];
        }
    }
}

/// Supernode `s`: its first column, its values (column-major, own columns then the pattern's
/// rows) and its pattern.
#[inline(always)]
fn supernode<'a>(
    symbolic: &'a Supernodes,
    values: &'a [f64],
    s: usize,
) -> (usize, &'a [f64], &'a [usize]) {
    let values_of = symbolic.value_ptr();
    (
        symbolic.columns(s).start,
        &values[values_of[s]..values_of[s + 1]],
        symbolic.pattern(s),
    )
}
