//! The implicit Schur complement: the reduced camera system S Δr = b_r − W V⁻¹ b_e solved by
//! preconditioned conjugate gradients without forming S. Each product
//! `S x = (U + D) x − W V⁻¹ (Wᵀ x)` is one pass over the eliminated blocks that reads their W
//! blocks from H, so memory grows with the observations, not with the camera pairs (5 000 BAL
//! cameras seen together: S alone would take ~8 GB, its factor as much again). Preconditioned by
//! Schur-Jacobi (`schur_jacobi`), as Ceres' ITERATIVE_SCHUR with SCHUR_JACOBI.
//!
//! Inexact Newton: CG stops when its quadratic model stops improving by more than a forcing term
//! η = min(η_max, √(‖b_r‖ / ‖b_r at the first solve‖)) (see `pcg`): loose far from the optimum
//! (where an exact step is wasted; Ceres keeps η = 0.1 throughout), tightening as the gradient
//! vanishes, so the last steps are as good as a direct solve's and the final cost is the same;
//! LM's step acceptance judges every step. Without the square root (η ∝ ‖b_r‖) the third LM
//! step of the 5 000-camera problem took 49 CG iterations of its 68.

use std::ops::{ControlFlow, Range};
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use super::super::budget::Budget;
use super::super::cholesky::NotPositiveDefinite;
use super::super::simd::has_wide_vectors;
use super::super::structure::BlockPattern;
use super::eliminate::{small_cholesky, small_cholesky_inverse, stopped};
use super::implicit_threads::Helper;
use super::pcg::{self, CgStop, CgWork};
use super::schur_jacobi::SchurJacobi;
use super::threads::H;
use super::{EliminatedBlocks, SchurPlan, CAMERA, ELIMINATED_PER_CHECK};

/// The loosest relative residual a step is solved to (Ceres' default η for LM).
const FORCING_MAX: f64 = 0.1;
/// The tightest; also the relative residual below which CG stops whatever its model says
/// (rounding).
const FORCING_MIN: f64 = 1e-10;
/// CG iterations per step at most (Ceres' `max_linear_solver_iterations` default).
const MAX_CG_ITERATIONS: usize = 500;

/// What the conjugate gradients did over a solve, for the Summary.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct CgStats {
    pub solves: usize,
    pub iterations: usize,
    pub max_iterations: usize,
}

/// Factorises (V⁻¹ and the preconditioner) and solves the reduced system iteratively; see the
/// module documentation.
pub struct ImplicitSchur {
    pub(super) eliminated: usize,
    /// Per eliminated block: dimension, first row, where its V⁻¹ starts, its neighbours.
    pub(super) blocks: EliminatedBlocks,
    pub(super) v_inverse: Vec<f64>,
    /// Per reduced block (full position `eliminated + k`): dimension and first reduced row.
    reduced_dim: Vec<usize>,
    reduced_offset: Vec<usize>,
    /// U's off-diagonal blocks between reduced blocks: (row block, column block, pair in H).
    u_pairs: Vec<(usize, usize, usize)>,
    /// The LM shift of the reduced rows (zeros without damping).
    pub(super) shift: Vec<f64>,
    pub(super) jacobi: SchurJacobi,
    rhs: Vec<f64>,
    solution: Vec<f64>,
    work: CgWork,
    first_rhs_norm: Option<f64>,
    /// When the solve's budget runs out, as the last factorisation saw it: CG starts no
    /// iteration past it (see `pcg::CgStop::deadline`).
    deadline: Option<Instant>,
    /// The loosest forcing term ([`FORCING_MAX`]; tests set 0: the residual tolerance alone).
    forcing_max: f64,
    /// A model decrease (in the reduced model's units, half of chi2's) too small to matter to
    /// the solve's stopping rule: CG stops once more iterations could add no more than this
    /// (see [`Self::set_negligible_decrease`]); 0: never.
    negligible_gain: f64,
    stats: CgStats,
    /// Why the implicit solver was chosen, for the Summary.
    reason: String,
    /// The eliminated blocks cut into parts, one per thread (see `implicit_threads`).
    pub(super) parts: Vec<Range<usize>>,
    /// The threads beside the caller's: their copies of the preconditioner and of a product.
    pub(super) helpers: Vec<Helper>,
}

impl std::fmt::Debug for ImplicitSchur {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ImplicitSchur")
            .field("eliminated", &self.eliminated)
            .field("reduced_dim", &self.shift.len())
            .field("stats", &self.stats)
            .finish()
    }
}

impl ImplicitSchur {
    /// `full` is the pattern laid out with `plan.ordering`.
    pub fn new(full: &BlockPattern, plan: &SchurPlan) -> Self {
        let ne = plan.eliminated;
        let blocks = EliminatedBlocks::of(full, ne);
        assert!(
            blocks.dim.iter().all(|&d| d <= 16),
            "eliminated variables have at most 16 dimensions"
        );
        let eliminated_rows = blocks.rows;
        let reduced_dim: Vec<usize> = full.dim[ne..].to_vec();
        let reduced_offset: Vec<usize> = full.offset[ne..]
            .iter()
            .map(|o| o - eliminated_rows)
            .collect();
        let mut u_pairs = Vec::new();
        for b in ne..full.dim.len() {
            for &(a, pair) in &full.column_blocks(b)[1..] {
                u_pairs.push((a - ne, b - ne, pair));
            }
        }
        let n = full.n - eliminated_rows;
        Self {
            eliminated: ne,
            v_inverse: vec![0.0; blocks.v_start[ne]],
            blocks,
            jacobi: SchurJacobi::new(reduced_dim.clone(), reduced_offset.clone()),
            reduced_dim,
            reduced_offset,
            u_pairs,
            shift: vec![0.0; n],
            rhs: vec![0.0; n],
            solution: vec![0.0; n],
            work: CgWork::new(n),
            first_rhs_norm: None,
            deadline: None,
            forcing_max: FORCING_MAX,
            negligible_gain: 0.0,
            stats: CgStats::default(),
            reason: plan.reason.clone(),
            parts: std::iter::once(0..ne).collect(),
            helpers: Vec::new(),
        }
    }

    pub fn eliminated_blocks(&self) -> usize {
        self.eliminated
    }

    pub fn reduced_blocks(&self) -> usize {
        self.reduced_dim.len()
    }

    pub fn reduced_dim(&self) -> usize {
        self.shift.len()
    }

    /// Caps the forcing term (tests: 0 solves every step to the residual tolerance alone).
    #[cfg(test)]
    pub(super) fn set_forcing_max(&mut self, forcing_max: f64) {
        self.forcing_max = forcing_max;
    }

    /// A chi2 decrease too small to matter to the solve: CG stops refining a step once more
    /// iterations could add no more than this to its predicted decrease. The iteration loop sets
    /// a tenth of what its function tolerance calls converged: the last step of a solve near
    /// its optimum (5 000 synthetic cameras: 49 CG iterations for a relative decrease of 5e-8)
    /// then takes a few iterations, not dozens.
    pub fn set_negligible_decrease(&mut self, chi2_decrease: f64) {
        self.negligible_gain = 0.5 * chi2_decrease.max(0.0);
    }

    pub fn stats(&self) -> CgStats {
        self.stats
    }

    pub fn reason(&self) -> &str {
        &self.reason
    }

    /// Numbers it holds beside H: V⁻¹, the preconditioner, the CG vectors and the threads'
    /// copies.
    pub fn numeric_len(&self) -> usize {
        let jacobi = self.jacobi.len();
        // Each thread beside the caller's: a copy of the preconditioner and a reduced vector.
        self.v_inverse.len()
            + jacobi
            + 8 * self.shift.len()
            + self.helpers.len() * (jacobi + self.shift.len())
    }

    /// "Factorises" H + diag(`shift`): every eliminated block's V⁻¹ and the preconditioner's
    /// blocks, part by part (see `implicit_threads`), the calling thread checking `budget` every
    /// [`ELIMINATED_PER_CHECK`] blocks (`Break`: stopped).
    pub fn factorize_within(
        &mut self,
        full: &BlockPattern,
        values: &[f64],
        shift: Option<&[f64]>,
        budget: &dyn Budget,
    ) -> Result<ControlFlow<()>, NotPositiveDefinite> {
        self.deadline = budget
            .remaining()
            .and_then(|left| Instant::now().checked_add(left));
        match shift {
            Some(shift) => self.shift.copy_from_slice(&shift[self.blocks.rows..]),
            None => self.shift.fill(0.0),
        }
        self.jacobi
            .reset(full, values, self.eliminated, &self.shift);
        if self
            .eliminate_parts((full, values), shift, budget)?
            .is_break()
        {
            return Ok(ControlFlow::Break(()));
        }
        self.jacobi.factorize(self.blocks.rows)?;
        Ok(ControlFlow::Continue(()))
    }

    /// The eliminated blocks `blocks`: each one's V⁻¹ into `v` (the slice of V⁻¹ that starts
    /// at the first one's) and its part of the preconditioner subtracted from `jacobi` (blocks
    /// laid out as the preconditioner's). The thread given `budget` checks it every
    /// [`ELIMINATED_PER_CHECK`] blocks and tells the others through `stop`, which they read as
    /// often.
    pub(super) fn eliminate_range(
        &self,
        blocks: Range<usize>,
        (v, jacobi): (&mut [f64], &mut [f64]),
        (h, shift): (H<'_>, Option<&[f64]>),
        budget: Option<&dyn Budget>,
        stop: &AtomicBool,
    ) -> Result<ControlFlow<()>, NotPositiveDefinite> {
        if has_wide_vectors() {
            // SAFETY: the CPU has the features `eliminate_wide` is compiled for.
            unsafe { eliminate_wide(self, blocks, (v, jacobi), (h, shift), budget, stop) }
        } else {
            eliminate_with(self, blocks, (v, jacobi), (h, shift), budget, stop)
        }
    }

    /// V⁻¹ of eliminated block `e` (with its shift) into `v`; errs at V's failing pivot.
    #[inline(always)]
    fn invert_v(
        &self,
        e: usize,
        v: &mut [f64],
        (full, values): H<'_>,
        shift: Option<&[f64]>,
    ) -> Result<(), NotPositiveDefinite> {
        let d = self.blocks.dim[e];
        let diagonal_pair = full.column_blocks(e)[0].1;
        for q in 0..d {
            for r in q..d {
                v[r * d + q] = values[full.value_index(diagonal_pair, true, r, q)];
            }
            if let Some(shift) = shift {
                v[q * d + q] += shift[self.blocks.offset[e] + q];
            }
        }
        small_cholesky(v, d).map_err(|i| NotPositiveDefinite {
            row: self.blocks.offset[e] + i,
        })?;
        small_cholesky_inverse(v, d);
        Ok(())
    }

    /// The preconditioner's blocks in `jacobi` −= W_k V⁻¹ W_kᵀ for every neighbour k of `e`
    /// (`v`: its V⁻¹).
    #[inline(always)]
    fn precondition_one<const D: usize, const K: usize>(
        &self,
        e: usize,
        v: &[f64],
        (full, values): H<'_>,
        jacobi: &mut [f64],
    ) {
        let d = if D > 0 { D } else { self.blocks.dim[e] };
        for nb in self.blocks.neighbours_of(e) {
            let dk = if K > 0 { K } else { self.reduced_dim[nb.block] };
            let mut w = [0.0; 16 * 16];
            for s in 0..d {
                let start = full.value_index(nb.w_pair, false, 0, s);
                w[s * dk..(s + 1) * dk].copy_from_slice(&values[start..start + dk]);
            }
            self.jacobi.subtract::<D, K>(jacobi, nb.block, &w, v, d);
        }
    }

    /// Solves with the last factorisation; `rhs` in the full layout, as
    /// [`super::SchurSolver::solve_in_place`]. The reduction, every product and the
    /// back-substitution run part by part.
    pub fn solve_in_place(&mut self, full: &BlockPattern, values: &[f64], rhs: &mut [f64]) {
        let h = (full, values);
        let base = self.blocks.rows;
        let mut reduced = std::mem::take(&mut self.rhs);
        reduced.copy_from_slice(&rhs[base..]);
        let mut helpers = std::mem::take(&mut self.helpers);
        self.reduce_parts(h, &rhs[..base], &mut reduced, &mut helpers);
        let norm = reduced.iter().map(|x| x * x).sum::<f64>().sqrt();
        let first = *self.first_rhs_norm.get_or_insert(norm);
        let forcing = if first > 0.0 {
            (norm / first)
                .sqrt()
                .clamp(FORCING_MIN.min(self.forcing_max), self.forcing_max)
        } else {
            self.forcing_max
        };
        let (mut solution, mut work) = (
            std::mem::take(&mut self.solution),
            std::mem::take(&mut self.work),
        );
        let outcome = pcg::solve(
            |x, y| self.product_parts(h, x, y, &mut helpers),
            |r, z| self.jacobi.apply(r, z),
            &reduced,
            &mut solution,
            CgStop {
                residual: FORCING_MIN,
                model: forcing,
                gain: self.negligible_gain,
                max_iterations: MAX_CG_ITERATIONS.min(reduced.len().max(1)),
                deadline: self.deadline,
            },
            &mut work,
        );
        self.stats.solves += 1;
        self.stats.iterations += outcome.iterations;
        self.stats.max_iterations = self.stats.max_iterations.max(outcome.iterations);
        rhs[base..].copy_from_slice(&solution);
        let (head, _) = rhs.split_at_mut(base);
        self.back_substitute_parts(h, head, &solution);
        (self.rhs, self.solution, self.work, self.helpers) = (reduced, solution, work, helpers);
    }

    /// `reduced −= W_e V_e⁻¹ b_e` for the eliminated blocks `blocks` (`b`: the eliminated rows).
    pub(super) fn reduce_range(
        &self,
        blocks: Range<usize>,
        h: H<'_>,
        b: &[f64],
        reduced: &mut [f64],
    ) {
        for e in blocks {
            let mut t = [0.0; 16];
            self.v_inverse_times(
                e,
                &b[self.blocks.offset[e]..self.blocks.offset[e] + self.blocks.dim[e]],
                &mut t,
            );
            self.subtract_w(e, h, &t, reduced);
        }
    }

    /// x_e = V_e⁻¹ (b_e − Σ_k W_kᵀ x_k) for the eliminated blocks `blocks`, in place in
    /// `rows` (their rows; it starts at row `first`), from the reduced `solution`.
    pub(super) fn back_substitute_range(
        &self,
        blocks: Range<usize>,
        h: H<'_>,
        (rows, first): (&mut [f64], usize),
        solution: &[f64],
    ) {
        for e in blocks {
            let (o, d) = (self.blocks.offset[e] - first, self.blocks.dim[e]);
            let mut be = [0.0; 16];
            be[..d].copy_from_slice(&rows[o..o + d]);
            self.subtract_wt(e, h, solution, &mut be);
            let mut xe = [0.0; 16];
            self.v_inverse_times(e, &be[..d], &mut xe);
            rows[o..o + d].copy_from_slice(&xe[..d]);
        }
    }

    /// out = V_e⁻¹ x.
    fn v_inverse_times(&self, e: usize, x: &[f64], out: &mut [f64; 16]) {
        let d = self.blocks.dim[e];
        let v = &self.v_inverse[self.blocks.v_range(e)];
        for i in 0..d {
            out[i] = (0..d).map(|j| v[i * d + j] * x[j]).sum();
        }
    }

    /// y_k −= W_k t for every neighbour k of `e`.
    fn subtract_w(&self, e: usize, (full, values): H<'_>, t: &[f64], y: &mut [f64]) {
        for nb in self.blocks.neighbours_of(e) {
            let (dk, ok) = (self.reduced_dim[nb.block], self.reduced_offset[nb.block]);
            for (s, ts) in t[..self.blocks.dim[e]].iter().enumerate() {
                let start = full.value_index(nb.w_pair, false, 0, s);
                for (yr, w) in y[ok..ok + dk].iter_mut().zip(&values[start..start + dk]) {
                    *yr -= w * ts;
                }
            }
        }
    }

    /// be −= Σ_k W_kᵀ x_k over the neighbours k of `e`.
    fn subtract_wt(&self, e: usize, (full, values): H<'_>, x: &[f64], be: &mut [f64]) {
        for nb in self.blocks.neighbours_of(e) {
            let (dk, ok) = (self.reduced_dim[nb.block], self.reduced_offset[nb.block]);
            for (s, b) in be[..self.blocks.dim[e]].iter_mut().enumerate() {
                let start = full.value_index(nb.w_pair, false, 0, s);
                *b -= values[start..start + dk]
                    .iter()
                    .zip(&x[ok..ok + dk])
                    .map(|(w, x)| w * x)
                    .sum::<f64>();
            }
        }
    }

    /// y = S x = (U + D) x − W V⁻¹ Wᵀ x, with the last factorisation's V⁻¹ and shift D, on the
    /// calling thread.
    #[cfg(test)]
    pub(super) fn product(&self, full: &BlockPattern, values: &[f64], x: &[f64], y: &mut [f64]) {
        self.product_parts((full, values), x, y, &mut []);
    }

    /// y = (U + D) x, the reduced blocks' own part of a product.
    pub(super) fn reduced_product(&self, h: H<'_>, x: &[f64], y: &mut [f64]) {
        for ((yi, xi), di) in y.iter_mut().zip(x).zip(&self.shift) {
            *yi = di * xi;
        }
        self.u_product(h, x, y);
    }

    /// y −= W V⁻¹ Wᵀ x over the eliminated blocks `blocks`.
    pub(super) fn eliminated_products(
        &self,
        blocks: Range<usize>,
        h: H<'_>,
        x: &[f64],
        y: &mut [f64],
    ) {
        if has_wide_vectors() {
            // SAFETY: the CPU has the features `products_wide` is compiled for.
            unsafe { products_wide(self, blocks, h, x, y) }
        } else {
            products_with(self, blocks, h, x, y)
        }
    }

    /// y_k −= W_k V⁻¹ Σ_l W_lᵀ x_l over the neighbours k, l of eliminated block `e`.
    #[inline(always)]
    fn eliminated_product<const D: usize, const K: usize>(
        &self,
        e: usize,
        (full, values): (&BlockPattern, &[f64]),
        x: &[f64],
        y: &mut [f64],
    ) {
        let d = if D > 0 { D } else { self.blocks.dim[e] };
        let around = self.blocks.neighbours_of(e);
        let mut t = [0.0; 16];
        for nb in around {
            let (dk, ok) = (
                if K > 0 { K } else { self.reduced_dim[nb.block] },
                self.reduced_offset[nb.block],
            );
            let xk = &x[ok..ok + dk];
            for (s, ts) in t[..d].iter_mut().enumerate() {
                let start = full.value_index(nb.w_pair, false, 0, s);
                let w = &values[start..start + dk];
                let mut acc = 0.0;
                for r in 0..dk {
                    acc += w[r] * xk[r];
                }
                *ts += acc;
            }
        }
        let v = &self.v_inverse[self.blocks.v_range(e)];
        let mut u = [0.0; 16];
        for i in 0..d {
            for j in 0..d {
                u[i] += v[i * d + j] * t[j];
            }
        }
        for nb in around {
            let (dk, ok) = (
                if K > 0 { K } else { self.reduced_dim[nb.block] },
                self.reduced_offset[nb.block],
            );
            let yk = &mut y[ok..ok + dk];
            for (s, us) in u[..d].iter().enumerate() {
                let start = full.value_index(nb.w_pair, false, 0, s);
                let w = &values[start..start + dk];
                for r in 0..dk {
                    yk[r] -= w[r] * us;
                }
            }
        }
    }

    /// y += U x for U's blocks in H (the diagonal ones' lower triangle mirrored).
    fn u_product(&self, (full, values): H<'_>, x: &[f64], y: &mut [f64]) {
        for k in 0..self.reduced_dim.len() {
            let (d, o) = (self.reduced_dim[k], self.reduced_offset[k]);
            let pair = full.column_blocks(self.eliminated + k)[0].1;
            for q in 0..d {
                y[o + q] += values[full.value_index(pair, true, q, q)] * x[o + q];
                for r in q + 1..d {
                    let h = values[full.value_index(pair, true, r, q)];
                    y[o + r] += h * x[o + q];
                    y[o + q] += h * x[o + r];
                }
            }
        }
        for &(a, b, pair) in &self.u_pairs {
            let (da, oa) = (self.reduced_dim[a], self.reduced_offset[a]);
            let (db, ob) = (self.reduced_dim[b], self.reduced_offset[b]);
            for q in 0..db {
                let start = full.value_index(pair, false, 0, q);
                let column = &values[start..start + da];
                let mut acc = 0.0;
                for r in 0..da {
                    y[oa + r] += column[r] * x[ob + q];
                    acc += column[r] * x[oa + r];
                }
                y[ob + q] += acc;
            }
        }
    }
}

/// [`ImplicitSchur::eliminate_range`]'s loop.
#[inline(always)]
fn eliminate_with(
    solver: &ImplicitSchur,
    blocks: Range<usize>,
    (v, jacobi): (&mut [f64], &mut [f64]),
    (h, shift): (H<'_>, Option<&[f64]>),
    budget: Option<&dyn Budget>,
    stop: &AtomicBool,
) -> Result<ControlFlow<()>, NotPositiveDefinite> {
    let v_first = solver.blocks.v_start[blocks.start];
    for (k, e) in blocks.enumerate() {
        if k % ELIMINATED_PER_CHECK == ELIMINATED_PER_CHECK - 1 && stopped(budget, stop) {
            return Ok(ControlFlow::Break(()));
        }
        let v = &mut v[solver.blocks.v_range_in(e, v_first)];
        solver.invert_v(e, v, h, shift)?;
        match (solver.blocks.dim[e], solver.blocks.camera_neighbours[e]) {
            (3, true) => solver.precondition_one::<3, CAMERA>(e, v, h, jacobi),
            _ => solver.precondition_one::<0, 0>(e, v, h, jacobi),
        }
    }
    Ok(ControlFlow::Continue(()))
}

#[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma"))]
fn eliminate_wide(
    solver: &ImplicitSchur,
    blocks: Range<usize>,
    numeric: (&mut [f64], &mut [f64]),
    inputs: (H<'_>, Option<&[f64]>),
    budget: Option<&dyn Budget>,
    stop: &AtomicBool,
) -> Result<ControlFlow<()>, NotPositiveDefinite> {
    eliminate_with(solver, blocks, numeric, inputs, budget, stop)
}

/// [`ImplicitSchur::eliminated_products`]' loop.
#[inline(always)]
fn products_with(solver: &ImplicitSchur, blocks: Range<usize>, h: H<'_>, x: &[f64], y: &mut [f64]) {
    for e in blocks {
        match (solver.blocks.dim[e], solver.blocks.camera_neighbours[e]) {
            (3, true) => solver.eliminated_product::<3, CAMERA>(e, h, x, y),
            _ => solver.eliminated_product::<0, 0>(e, h, x, y),
        }
    }
}

#[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma"))]
fn products_wide(solver: &ImplicitSchur, blocks: Range<usize>, h: H<'_>, x: &[f64], y: &mut [f64]) {
    products_with(solver, blocks, h, x, y)
}
