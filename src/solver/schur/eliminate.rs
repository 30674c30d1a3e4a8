//! One numeric factorisation: U copied into S (with the LM shift), then every eliminated block
//! in turn: its V⁻¹, Y = W V⁻¹ and S −= Y Wᵀ over its neighbour pairs; then S is factorised.
//! The small fixed-size kernels (a point's 3×3 V, a camera pair's 9×9 update) live here too.

use std::ops::ControlFlow;
use std::time::Instant;

use std::ops::Range;
use std::sync::atomic::{AtomicBool, Ordering};

use super::super::budget::{Budget, Unlimited};
use super::super::cholesky::NotPositiveDefinite;
use super::super::simd::has_wide_vectors;
use super::super::structure::BlockPattern;
use super::avx512;
use super::threads::{Part, View};
use super::{Neighbour, SchurSolver, CAMERA, ELIMINATED_PER_CHECK};

impl SchurSolver {
    /// Eliminates with the full matrix `values` (lower triangle in `full`'s layout) plus
    /// `diag(shift)` when given (LM damping, so H needs no damped copy), and factorises S.
    pub fn factorize(
        &mut self,
        full: &BlockPattern,
        values: &[f64],
        shift: Option<&[f64]>,
    ) -> Result<(), NotPositiveDefinite> {
        match self.factorize_within(full, values, shift, &Unlimited)? {
            ControlFlow::Continue(()) => Ok(()),
            ControlFlow::Break(()) => unreachable!("an unlimited budget never stops"),
        }
    }

    /// [`Self::factorize`] within `budget`: checked every [`ELIMINATED_PER_CHECK`] eliminated
    /// blocks and before S's factorisation, which is one uninterruptible call and is not started
    /// (nor is the elimination) when its predicted time exceeds the time left. `Break`: stopped;
    /// nothing is factorised and the caller must not solve with this factorisation.
    pub fn factorize_within(
        &mut self,
        full: &BlockPattern,
        values: &[f64],
        shift: Option<&[f64]>,
        budget: &dyn Budget,
    ) -> Result<ControlFlow<()>, NotPositiveDefinite> {
        // Eliminating is wasted when S's factorisation cannot fit afterwards.
        if !self.reduced_cost.fits(budget) {
            return Ok(ControlFlow::Break(()));
        }
        self.s_values.fill(0.0);
        for &(from, to) in &self.u_map {
            self.s_values[to] = values[from];
        }
        if let Some(shift) = shift {
            let n = self.reduced.n;
            let dense = self.is_dense();
            for (i, add) in shift[self.blocks.rows..].iter().enumerate() {
                let at = if dense {
                    i * n + i
                } else {
                    self.reduced.diagonal_index(i)
                };
                self.s_values[at] += add;
            }
        }
        let eliminated = self.eliminate_parts(full, values, shift, budget)?;
        if eliminated.is_break()
            || budget.checkpoint().is_break()
            || !self.reduced_cost.fits(budget)
        {
            return Ok(ControlFlow::Break(()));
        }
        let started = Instant::now();
        let factorized =
            self.backend
                .factorize(&self.reduced, &mut self.s_values, self.blocks.rows);
        self.reduced_cost.measure(started.elapsed());
        factorized.map(ControlFlow::Continue)
    }
}

impl View<'_> {
    /// Eliminates block `e` (of dimension `D`, or any when `D` is 0; its neighbours all of
    /// dimension `K`, or any when `K` is 0): V⁻¹, Y = W V⁻¹ and
    /// S −= Y Wᵀ over every pair of its neighbours. Errs with the failing pivot of V.
    // The const-generic kernel BA time is spent in, monomorphised per block size and inlined
    // into its caller, as are its parts.
    #[inline(always)]
    fn eliminate<const D: usize, const K: usize, const FUSED: bool, const WIDEST: bool>(
        &self,
        part: &mut Part<'_>,
        e: usize,
        full: &BlockPattern,
        values: &[f64],
        shift: Option<&[f64]>,
    ) -> Result<(), usize> {
        let d = if D > 0 { D } else { self.blocks.dim[e] };
        let reduced = self.reduced;
        let dense_n = self.dense_n;
        let v = &mut part.v_inverse[self.blocks.v_range_in(e, part.v_first)];
        let diagonal_pair = full.column_blocks(e)[0].1;
        for q in 0..d {
            for r in q..d {
                v[r * d + q] = values[full.value_index(diagonal_pair, true, r, q)];
            }
        }
        if let Some(shift) = shift {
            for q in 0..d {
                v[q * d + q] += shift[self.blocks.offset[e] + q];
            }
        }
        small_cholesky(v, d)?;
        small_cholesky_inverse(v, d);
        let around = self.blocks.neighbours_of(e);
        let local = self.gather_w_and_y::<D, K>(part, around, d, e, full, values);
        // S_kl −= Y_k W_lᵀ for l ≤ k: column q of the block is the axpy Σ_t Y_k[:, t] W_l[q, t].
        let blocks = &self.s_blocks[self.s_block_start[e]..self.s_block_start[e + 1]];
        let mut next = 0;
        let mut local_k = 0;
        for (k, nk) in around.iter().enumerate() {
            let dk = if K > 0 { K } else { reduced.dim[nk.block] };
            let y = &part.y_local[local_k..local_k + dk * d];
            let mut local_l = 0;
            for (l, nl) in around[..=k].iter().enumerate() {
                let dl = if K > 0 { K } else { reduced.dim[nl.block] };
                let block = blocks[next];
                next += 1;
                let w = &part.w_local[local_l..local_l + dl * d];
                local_l += dl * d;
                match dense_n {
                    // Dense S: a diagonal block may be written whole (the upper half is unread);
                    // the sparse S keeps only its lower triangle.
                    _ if WIDEST && D == 3 && K == CAMERA => {
                        let columns = match dense_n {
                            Some(n) => avx512::BlockColumns::dense(block, n),
                            None => avx512::BlockColumns {
                                starts: std::array::from_fn(|q| {
                                    let first = if k == l { q } else { 0 };
                                    reduced.value_index(block, k == l, first, q)
                                }),
                                lower_only: k == l,
                            },
                        };
                        let (y, w) = (y.try_into(), w.try_into());
                        let (y, w) = (y.expect("K×3"), w.expect("K×3"));
                        // SAFETY: `WIDEST` is only compiled into the AVX-512 twin, chosen when
                        // the CPU has it.
                        unsafe { avx512::subtract_camera_product(part.s_values, &columns, y, w) }
                    }
                    Some(n) if D > 0 && K == CAMERA => {
                        subtract_product::<D, CAMERA, FUSED>(&mut part.s_values[block..], n, y, w)
                    }
                    None if D > 0 && K == CAMERA => subtract_product_sparse::<D, CAMERA, FUSED>(
                        part.s_values,
                        reduced,
                        (block, k == l),
                        y,
                        w,
                    ),
                    _ => {
                        self.subtract_product_any(part.s_values, (block, k == l), (dk, dl, d), y, w)
                    }
                }
            }
            local_k += dk * d;
        }
        debug_assert_eq!(local_k, local);
        Ok(())
    }

    /// W of every neighbour of block `e` (column by column, each contiguous in the full
    /// pattern) into `part.w_local`, and Y = W V⁻¹ into `part.y_local`; returns the scalars each
    /// holds.
    #[inline(always)]
    fn gather_w_and_y<const D: usize, const K: usize>(
        &self,
        part: &mut Part<'_>,
        around: &[Neighbour],
        d: usize,
        e: usize,
        full: &BlockPattern,
        values: &[f64],
    ) -> usize {
        let v = &part.v_inverse[self.blocks.v_range_in(e, part.v_first)];
        let mut local = 0;
        for nb in around {
            let dk = if K > 0 { K } else { self.reduced.dim[nb.block] };
            let w = &mut part.w_local[local..local + dk * d];
            for t in 0..d {
                let start = full.value_index(nb.w_pair, false, 0, t);
                for (to, from) in w[t * dk..(t + 1) * dk]
                    .iter_mut()
                    .zip(&values[start..start + dk])
                {
                    *to = *from;
                }
            }
            let y = &mut part.y_local[local..local + dk * d];
            y.fill(0.0);
            for t in 0..d {
                let yt = &mut y[t * dk..(t + 1) * dk];
                for s in 0..d {
                    let factor = v[s * d + t];
                    for (yr, wr) in yt.iter_mut().zip(&w[s * dk..(s + 1) * dk]) {
                        *yr += wr * factor;
                    }
                }
            }
            local += dk * d;
        }
        local
    }

    /// S_kl −= Y_k W_lᵀ for blocks of any size (`block`: where S's block starts, or its pair in
    /// the sparse S; `diagonal`: only its lower triangle is written).
    #[inline(always)]
    fn subtract_product_any(
        &self,
        s_values: &mut [f64],
        (block, diagonal): (usize, bool),
        (dk, dl, d): (usize, usize, usize),
        y: &[f64],
        w: &[f64],
    ) {
        for q in 0..dl {
            let first = if diagonal { q } else { 0 };
            let start = match self.dense_n {
                Some(n) => block + q * n + first,
                None => self.reduced.value_index(block, diagonal, first, q),
            };
            let column = &mut s_values[start..start + dk - first];
            for t in 0..d {
                let factor = w[t * dl + q];
                let yt = &y[t * dk + first..(t + 1) * dk];
                for (s, yr) in column.iter_mut().zip(yt) {
                    *s -= yr * factor;
                }
            }
        }
    }
}

/// One thread's share of an elimination: its eliminated blocks, H (pattern, values, the LM
/// shift), and the budget (the calling thread's only, which tells the others through `stop`).
pub(super) struct Pass<'a> {
    pub(super) blocks: Range<usize>,
    pub(super) inputs: (&'a BlockPattern, &'a [f64], Option<&'a [f64]>),
    pub(super) budget: Option<&'a dyn Budget>,
    pub(super) stop: &'a AtomicBool,
}

/// Eliminates `pass`'s blocks into `part`; errs at the first V that is not positive definite.
/// `Break`: the budget stopped it part way (S is then incomplete).
#[inline(always)]
fn eliminate_all<const FUSED: bool, const WIDEST: bool>(
    view: &View<'_>,
    part: &mut Part<'_>,
    pass: Pass<'_>,
) -> Result<ControlFlow<()>, NotPositiveDefinite> {
    let Pass {
        blocks,
        inputs: (full, values, shift),
        budget,
        stop,
    } = pass;
    for (k, e) in blocks.enumerate() {
        if k % ELIMINATED_PER_CHECK == ELIMINATED_PER_CHECK - 1 && stopped(budget, stop) {
            return Ok(ControlFlow::Break(()));
        }
        let result = match (view.blocks.dim[e], view.blocks.camera_neighbours[e]) {
            (3, true) => view.eliminate::<3, CAMERA, FUSED, WIDEST>(part, e, full, values, shift),
            (3, false) => view.eliminate::<3, 0, FUSED, false>(part, e, full, values, shift),
            _ => view.eliminate::<0, 0, FUSED, false>(part, e, full, values, shift),
        };
        result.map_err(|i| NotPositiveDefinite {
            row: view.blocks.offset[e] + i,
        })?;
    }
    Ok(ControlFlow::Continue(()))
}

/// Whether to stop: the calling thread asks `budget` (and tells the others), they read `stop`.
/// Also the implicit solver's parts.
#[inline(always)]
pub(super) fn stopped(budget: Option<&dyn Budget>, stop: &AtomicBool) -> bool {
    match budget {
        Some(budget) => {
            let stopped = budget.checkpoint().is_break();
            if stopped {
                stop.store(true, Ordering::Relaxed);
            }
            stopped
        }
        None => stop.load(Ordering::Relaxed),
    }
}

#[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma"))]
fn eliminate_all_wide(
    view: &View<'_>,
    part: &mut Part<'_>,
    pass: Pass<'_>,
) -> Result<ControlFlow<()>, NotPositiveDefinite> {
    eliminate_all::<true, false>(view, part, pass)
}

#[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx512f,avx2,fma"))]
fn eliminate_all_widest(
    view: &View<'_>,
    part: &mut Part<'_>,
    pass: Pass<'_>,
) -> Result<ControlFlow<()>, NotPositiveDefinite> {
    eliminate_all::<true, true>(view, part, pass)
}

/// [`eliminate_all`] with the widest kernels the CPU has.
pub(super) fn eliminate_blocks(
    view: &View<'_>,
    part: &mut Part<'_>,
    pass: Pass<'_>,
) -> Result<ControlFlow<()>, NotPositiveDefinite> {
    if avx512::available() {
        // SAFETY: the CPU has the features `eliminate_all_widest` is compiled for.
        unsafe { eliminate_all_widest(view, part, pass) }
    } else if has_wide_vectors() {
        // SAFETY: the CPU has the features `eliminate_all_wide` is compiled for.
        unsafe { eliminate_all_wide(view, part, pass) }
    } else {
        eliminate_all::<false, false>(view, part, pass)
    }
}

/// `S[.., ..] −= Y Wᵀ` for column-major `y`, `w` (K × D) into the K×K block of a column-major
/// matrix with leading dimension `n` that starts at `s[0]`. `FUSED`: the products as fused
/// multiply-adds, for callers compiled with FMA (without it `mul_add` is a library call).
#[inline(always)]
fn subtract_product<const D: usize, const K: usize, const FUSED: bool>(
    s: &mut [f64],
    n: usize,
    y: &[f64],
    w: &[f64],
) {
    let (y, w) = (&y[..K * D], &w[..K * D]);
    for q in 0..K {
        let column = &mut s[q * n..q * n + K];
        let acc = product_column::<D, K, FUSED>(y, w, q);
        for r in 0..K {
            column[r] -= acc[r];
        }
    }
}

/// Column `q` of Y Wᵀ (Y and W both `D` columns of `K` scalars).
#[inline(always)]
fn product_column<const D: usize, const K: usize, const FUSED: bool>(
    y: &[f64],
    w: &[f64],
    q: usize,
) -> [f64; K] {
    let mut acc = [0.0; K];
    for t in 0..D {
        let factor = w[t * K + q];
        for r in 0..K {
            acc[r] = if FUSED {
                y[t * K + r].mul_add(factor, acc[r])
            } else {
                acc[r] + y[t * K + r] * factor
            };
        }
    }
    acc
}

/// [`subtract_product`] into block `pair` of the sparse S (`diagonal`: only its lower triangle
/// is stored, so only that is written).
#[inline(always)]
fn subtract_product_sparse<const D: usize, const K: usize, const FUSED: bool>(
    s: &mut [f64],
    reduced: &BlockPattern,
    (pair, diagonal): (usize, bool),
    y: &[f64],
    w: &[f64],
) {
    let (y, w) = (&y[..K * D], &w[..K * D]);
    for q in 0..K {
        let acc = product_column::<D, K, FUSED>(y, w, q);
        let first = if diagonal { q } else { 0 };
        let start = reduced.value_index(pair, diagonal, first, q);
        for (to, a) in s[start..start + K - first].iter_mut().zip(&acc[first..]) {
            *to -= a;
        }
    }
}

/// In-place Cholesky of the d×d row-major matrix `a` (lower triangle read and written).
/// On failure returns the row of the non-positive pivot.
/// In-place Cholesky of a small d×d block (lower triangle, row-major; the upper triangle is
/// left as it was). `Err(j)`: the pivot of row `j` is not positive and finite. Also the
/// incremental factor's diagonal blocks (`solver::incremental`).
#[inline(always)]
pub(in crate::solver) fn small_cholesky(a: &mut [f64], d: usize) -> Result<(), usize> {
    for j in 0..d {
        let mut pivot = a[j * d + j];
        for k in 0..j {
            pivot -= a[j * d + k] * a[j * d + k];
        }
        if !(pivot > 0.0 && pivot.is_finite()) {
            return Err(j);
        }
        let pivot = pivot.sqrt();
        a[j * d + j] = pivot;
        for i in j + 1..d {
            let mut s = a[i * d + j];
            for k in 0..j {
                s -= a[i * d + k] * a[j * d + k];
            }
            a[i * d + j] = s / pivot;
        }
    }
    Ok(())
}

/// Replaces the factor L of [`small_cholesky`] (lower triangle of `a`) by (L Lᵀ)⁻¹, both
/// triangles.
#[inline(always)]
pub(super) fn small_cholesky_inverse(a: &mut [f64], d: usize) {
    let mut inverse = [0.0; 256];
    assert!(d <= 16, "eliminated variables have at most 16 dimensions");
    for c in 0..d {
        // Solve L Lᵀ x = e_c.
        let mut x = [0.0; 16];
        x[c] = 1.0;
        for i in 0..d {
            let mut s = x[i];
            for k in 0..i {
                s -= a[i * d + k] * x[k];
            }
            x[i] = s / a[i * d + i];
        }
        for i in (0..d).rev() {
            let mut s = x[i];
            for k in i + 1..d {
                s -= a[k * d + i] * x[k];
            }
            x[i] = s / a[i * d + i];
        }
        for r in 0..d {
            inverse[r * d + c] = x[r];
        }
    }
    a.copy_from_slice(&inverse[..d * d]);
}
