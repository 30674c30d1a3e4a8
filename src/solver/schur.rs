//! The Schur complement: eliminate landmark-like variables first and solve the reduced system.
//!
//! Order the normal equations as
//!
//! ```text
//! [ V  Wᵀ ] [Δe]   [b_e]
//! [ W  U  ] [Δr] = [b_r]
//! ```
//!
//! with `e` the eliminated variables (BA points), which no factor connects to each other, so V is
//! block diagonal. Then `S = U − W V⁻¹ Wᵀ` (the reduced camera system) gives
//! `S Δr = b_r − W V⁻¹ b_e` and `Δe = V⁻¹ (b_e − Wᵀ Δr)`. Each V block is a few scalars; S is
//! factorised densely when it is small (few cameras: dense kernels beat any sparse bookkeeping)
//! and with the sparse supernodal Cholesky otherwise. This is exactly sparse Cholesky with the
//! eliminated variables ordered first, but done by block arithmetic: a general sparse
//! factorisation spends most of its time on thousands of 3-column supernodes.
//!
//! Which variables to eliminate is a property of the problem ([`crate::problem::Problem::eliminate`]):
//! every free variable of the listed kinds, except that a variable sharing a factor with an
//! already chosen one stays in the reduced system (V must stay block diagonal).

use std::borrow::Borrow;

use dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::{self as dense_llt, LltError, LltRegularization};
use faer::linalg::cholesky::llt::solve as dense_llt_solve;
use faer::sparse::linalg::SupernodalThreshold;
use faer::{Conj, MatMut, MatRef, Par, Spec};

use super::cholesky::{NotPositiveDefinite, SparseCholesky, SymbolicError};
use super::linearize::{free_adjacency, free_blocks};
use super::options::LinearSolverChoice;
use super::simd::has_wide_vectors;
use super::structure::{BlockOrdering, BlockPattern};
use crate::factors::FactorEntry;
use crate::problem::Values;

/// Auto picks a dense reduced system up to this many scalar unknowns (≈110 BAL cameras): a dense
/// Cholesky of that size costs ~30 ms, about a sparse one's bookkeeping on a dense-ish S.
const DENSE_AUTO_MAX: usize = 1000;

/// How one solve eliminates: decided once per problem structure.
#[derive(Debug, Clone)]
pub struct SchurPlan {
    /// Order of the whole free-variable graph: eliminated blocks first, then the reduced ones in
    /// the order of `reduced`.
    pub ordering: BlockOrdering,
    /// Number of eliminated blocks (they hold positions `0..eliminated`).
    pub eliminated: usize,
    /// The reduced system's graph and order; block `k` is full position `eliminated + k`.
    reduced: BlockOrdering,
    pub dense: bool,
}

/// Plans the Schur complement for the free variables (`fixed[v]` false) whose kind is in
/// `kinds`; `None` when it does not apply (no such variable, nothing left to reduce to, or the
/// choice is plain sparse Cholesky).
pub fn plan<E: Borrow<FactorEntry>>(
    factors: &[E],
    values: &Values,
    fixed: &[bool],
    kinds: &[&str],
    choice: LinearSolverChoice,
) -> Option<SchurPlan> {
    if kinds.is_empty() || choice == LinearSolverChoice::SparseCholesky {
        return None;
    }
    let (block_of_var, count) = free_blocks(fixed.iter().copied());
    let adjacency = free_adjacency(factors, fixed);
    let mut dims = vec![0; count];
    let mut eliminate = vec![false; count];
    for (v, block) in block_of_var.iter().enumerate() {
        let Some(b) = *block else { continue };
        let variable = values.variable(v);
        dims[b] = variable.tangent_dim();
        if kinds.contains(&variable.kind()) && !adjacency[b].iter().any(|&n| eliminate[n]) {
            eliminate[b] = true;
        }
    }
    let eliminated = eliminate.iter().filter(|&&e| e).count();
    if eliminated == 0 || eliminated == count {
        return None;
    }
    // Reduced graph: direct neighbours, plus every pair of blocks sharing an eliminated one.
    let mut reduced_index = vec![usize::MAX; count];
    let mut next = 0;
    for b in 0..count {
        if !eliminate[b] {
            reduced_index[b] = next;
            next += 1;
        }
    }
    let reduced_count = next;
    let mut reduced_adjacency = vec![Vec::new(); reduced_count];
    for b in 0..count {
        if eliminate[b] {
            let around: Vec<usize> = adjacency[b].iter().map(|&n| reduced_index[n]).collect();
            for &x in &around {
                reduced_adjacency[x].extend(around.iter().filter(|&&y| y != x));
            }
        } else {
            reduced_adjacency[reduced_index[b]].extend(
                adjacency[b]
                    .iter()
                    .filter(|&&n| !eliminate[n])
                    .map(|&n| reduced_index[n]),
            );
        }
    }
    for list in &mut reduced_adjacency {
        list.sort_unstable();
        list.dedup();
    }
    let reduced_dim: usize = (0..count).filter(|&b| !eliminate[b]).map(|b| dims[b]).sum();
    let dense = match choice {
        LinearSolverChoice::DenseSchur => true,
        LinearSolverChoice::SparseSchur => false,
        _ => reduced_dim <= DENSE_AUTO_MAX,
    };
    let reduced = if dense {
        // Every pair present, in the given order: the pattern is the dense lower triangle.
        let all = (0..reduced_count)
            .map(|x| (0..reduced_count).filter(|&y| y != x).collect())
            .collect();
        BlockOrdering {
            adjacency: all,
            position: (0..reduced_count).collect(),
            block_at: (0..reduced_count).collect(),
        }
    } else {
        BlockOrdering::amd(reduced_adjacency)
    };
    let mut position = vec![0; count];
    let mut next_eliminated = 0;
    for b in 0..count {
        position[b] = if eliminate[b] {
            next_eliminated += 1;
            next_eliminated - 1
        } else {
            eliminated + reduced.position[reduced_index[b]]
        };
    }
    let mut block_at = vec![0; count];
    for (b, &p) in position.iter().enumerate() {
        block_at[p] = b;
    }
    Some(SchurPlan {
        ordering: BlockOrdering {
            adjacency,
            position,
            block_at,
        },
        eliminated,
        reduced,
        dense,
    })
}

/// One neighbour (reduced block) of an eliminated block: its W block in the full pattern, and
/// where Y = W V⁻¹ of that pair is kept.
#[derive(Debug, Clone, Copy)]
struct Neighbour {
    /// Reduced block number (full position − eliminated).
    block: usize,
    w_pair: usize,
    y_offset: usize,
}

enum Backend {
    /// S is `s_values` as a column-major n×n matrix (lower triangle used).
    Dense { mem: MemBuffer },
    /// S is `s_values` in the reduced [`BlockPattern`]'s layout.
    Sparse(SparseCholesky),
}

/// Factorises the normal equations by eliminating a block-diagonal part first; see the module
/// documentation.
pub struct SchurSolver {
    eliminated: usize,
    /// Scalar rows of the eliminated part; reduced scalar row `i` is full row `eliminated_rows + i`.
    eliminated_rows: usize,
    /// Scalar dimension and first row of every eliminated block, and where its V⁻¹ starts.
    dim: Vec<usize>,
    offset: Vec<usize>,
    v_start: Vec<usize>,
    v_inverse: Vec<f64>,
    neighbour_start: Vec<usize>,
    neighbours: Vec<Neighbour>,
    /// Per eliminated block: whether all its neighbours are [`CAMERA`]-sized (fixed-size kernels).
    camera_neighbours: Vec<bool>,
    /// Per eliminated block, the S block of every neighbour pair (k, l ≤ k), row by row: a pair
    /// of the reduced pattern (sparse) or the index of the block's (0, 0) entry (dense).
    s_block_start: Vec<usize>,
    s_blocks: Vec<usize>,
    /// Y = W V⁻¹ per (eliminated block, neighbour), column-major (dk × d).
    y_values: Vec<f64>,
    /// (full pattern value index, S value index) of every U entry.
    u_map: Vec<(usize, usize)>,
    reduced: BlockPattern,
    s_values: Vec<f64>,
    backend: Backend,
    /// W of the current eliminated block's neighbours, column-major like Y.
    w_local: Vec<f64>,
    rhs: Vec<f64>,
}

impl std::fmt::Debug for SchurSolver {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SchurSolver")
            .field("eliminated", &self.eliminated)
            .field("reduced_dim", &self.reduced.n)
            .field("dense", &self.is_dense())
            .finish()
    }
}

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
        let eliminated_rows = full.n - n;
        // Where an S block (a ≥ b, reduced positions) starts, and element (r, q) of it.
        let dense_index = |a: usize, b: usize, r: usize, q: usize| {
            (reduced.offset[b] + q) * n + reduced.offset[a] + r
        };
        let mut dim = Vec::with_capacity(ne);
        let mut offset = Vec::with_capacity(ne);
        let mut v_start = Vec::with_capacity(ne + 1);
        let mut neighbour_start = Vec::with_capacity(ne + 1);
        let mut neighbours = Vec::new();
        let mut s_block_start = Vec::with_capacity(ne + 1);
        let mut s_blocks = Vec::new();
        let (mut v_len, mut y_len, mut w_max) = (0, 0, 0);
        for e in 0..ne {
            let d = full.dim[e];
            dim.push(d);
            offset.push(full.offset[e]);
            v_start.push(v_len);
            v_len += d * d;
            neighbour_start.push(neighbours.len());
            s_block_start.push(s_blocks.len());
            let first = neighbours.len();
            let mut w_len = 0;
            for &(a, w_pair) in full.column_blocks(e) {
                if a == e {
                    continue;
                }
                assert!(
                    a >= ne,
                    "eliminated blocks {a} and {e} share a factor: a planning bug"
                );
                neighbours.push(Neighbour {
                    block: a - ne,
                    w_pair,
                    y_offset: y_len,
                });
                y_len += full.dim[a] * d;
                w_len += full.dim[a] * d;
            }
            w_max = w_max.max(w_len);
            // Neighbours are sorted by position, so (k, l ≤ k) is a lower block of S.
            for k in first..neighbours.len() {
                for l in first..=k {
                    let (a, b) = (neighbours[k].block, neighbours[l].block);
                    s_blocks.push(if plan.dense {
                        dense_index(a, b, 0, 0)
                    } else {
                        reduced.pair(a, b).expect(
                            "the reduced pattern holds every pair sharing an eliminated block",
                        )
                    });
                }
            }
        }
        v_start.push(v_len);
        neighbour_start.push(neighbours.len());
        s_block_start.push(s_blocks.len());
        let camera_neighbours = (0..ne)
            .map(|e| {
                neighbours[neighbour_start[e]..neighbour_start[e + 1]]
                    .iter()
                    .all(|n| reduced.dim[n.block] == CAMERA)
            })
            .collect();
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
                        let to = if plan.dense {
                            dense_index(ra, rb, r, q)
                        } else {
                            reduced.value_index(s_pair, diagonal, r, q)
                        };
                        u_map.push((full.value_index(pair, diagonal, r, q), to));
                    }
                }
            }
        }
        let (backend, s_len) = if plan.dense {
            let mem = MemBuffer::new(dense_llt::cholesky_in_place_scratch::<f64>(
                n,
                Par::Seq,
                Spec::default(),
            ));
            (Backend::Dense { mem }, n * n)
        } else {
            let chol = SparseCholesky::analyze(&reduced, SupernodalThreshold::FORCE_SUPERNODAL)?;
            (Backend::Sparse(chol), reduced.nnz())
        };
        Ok(Self {
            eliminated: ne,
            eliminated_rows,
            dim,
            offset,
            v_start,
            v_inverse: vec![0.0; v_len],
            neighbour_start,
            neighbours,
            camera_neighbours,
            s_block_start,
            s_blocks,
            y_values: vec![0.0; y_len],
            u_map,
            s_values: vec![0.0; s_len],
            w_local: vec![0.0; w_max],
            rhs: vec![0.0; n],
            reduced,
            backend,
        })
    }

    pub fn is_dense(&self) -> bool {
        matches!(self.backend, Backend::Dense { .. })
    }

    pub fn eliminated_blocks(&self) -> usize {
        self.eliminated
    }

    pub fn reduced_blocks(&self) -> usize {
        self.reduced.dim.len()
    }

    pub fn reduced_dim(&self) -> usize {
        self.reduced.n
    }

    /// Nonzeros of the reduced system's factor (dense: the lower triangle).
    pub fn factor_nnz(&self) -> usize {
        match &self.backend {
            Backend::Dense { .. } => self.reduced.n * (self.reduced.n + 1) / 2,
            Backend::Sparse(chol) => chol.factor_nnz(),
        }
    }

    /// Eliminates with the full matrix `values` (lower triangle in `full`'s layout) plus
    /// `diag(shift)` when given (LM damping, so H needs no damped copy), and factorises S.
    pub fn factorize(
        &mut self,
        full: &BlockPattern,
        values: &[f64],
        shift: Option<&[f64]>,
    ) -> Result<(), NotPositiveDefinite> {
        self.s_values.fill(0.0);
        for &(from, to) in &self.u_map {
            self.s_values[to] = values[from];
        }
        if let Some(shift) = shift {
            let n = self.reduced.n;
            let dense = self.is_dense();
            for (i, add) in shift[self.eliminated_rows..].iter().enumerate() {
                let at = if dense {
                    i * n + i
                } else {
                    self.reduced.diagonal_index(i)
                };
                self.s_values[at] += add;
            }
        }
        if has_wide_vectors() {
            // SAFETY: the CPU has the features `eliminate_all_wide` is compiled for.
            unsafe { eliminate_all_wide(self, full, values, shift) }
        } else {
            eliminate_all(self, full, values, shift)
        }?;
        let (offset_rows, n) = (self.eliminated_rows, self.reduced.n);
        match &mut self.backend {
            Backend::Dense { mem } => dense_llt::cholesky_in_place(
                MatMut::from_column_major_slice_mut(&mut self.s_values, n, n),
                LltRegularization::default(),
                Par::Seq,
                MemStack::new(mem),
                Spec::default(),
            )
            .map(|_| ())
            .map_err(|LltError::NonPositivePivot { index }| NotPositiveDefinite {
                row: offset_rows + index,
            }),
            Backend::Sparse(chol) => {
                chol.factorize(&self.reduced, &self.s_values)
                    .map_err(|e| NotPositiveDefinite {
                        row: offset_rows + e.row,
                    })
            }
        }
    }

    /// Eliminates block `e` (of dimension `D`, or any when `D` is 0; its neighbours all of
    /// dimension `K`, or any when `K` is 0): V⁻¹, Y = W V⁻¹ and
    /// S −= Y Wᵀ over every pair of its neighbours. Errs with the failing pivot of V.
    #[inline(always)]
    fn eliminate<const D: usize, const K: usize>(
        &mut self,
        e: usize,
        full: &BlockPattern,
        values: &[f64],
        shift: Option<&[f64]>,
    ) -> Result<(), usize> {
        let d = if D > 0 { D } else { self.dim[e] };
        let reduced = &self.reduced;
        let dense_n = match self.backend {
            Backend::Dense { .. } => Some(reduced.n),
            Backend::Sparse(_) => None,
        };
        let v = &mut self.v_inverse[self.v_start[e]..self.v_start[e + 1]];
        let diagonal_pair = full.column_blocks(e)[0].1;
        for q in 0..d {
            for r in q..d {
                v[r * d + q] = values[full.value_index(diagonal_pair, true, r, q)];
            }
        }
        if let Some(shift) = shift {
            for q in 0..d {
                v[q * d + q] += shift[self.offset[e] + q];
            }
        }
        small_cholesky(v, d)?;
        small_cholesky_inverse(v, d);
        let around = &self.neighbours[self.neighbour_start[e]..self.neighbour_start[e + 1]];
        // W column by column (each contiguous in the full pattern), then Y = W V⁻¹.
        let mut local = 0;
        for nb in around {
            let dk = if K > 0 { K } else { reduced.dim[nb.block] };
            let w = &mut self.w_local[local..local + dk * d];
            for t in 0..d {
                let start = full.value_index(nb.w_pair, false, 0, t);
                for (to, from) in w[t * dk..(t + 1) * dk]
                    .iter_mut()
                    .zip(&values[start..start + dk])
                {
                    *to = *from;
                }
            }
            let y = &mut self.y_values[nb.y_offset..nb.y_offset + dk * d];
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
        // S_kl −= Y_k W_lᵀ for l ≤ k: column q of the block is the axpy Σ_t Y_k[:, t] W_l[q, t].
        let blocks = &self.s_blocks[self.s_block_start[e]..self.s_block_start[e + 1]];
        let mut next = 0;
        let mut local_k = 0;
        for (k, nk) in around.iter().enumerate() {
            let dk = if K > 0 { K } else { reduced.dim[nk.block] };
            let y = &self.y_values[nk.y_offset..nk.y_offset + dk * d];
            let mut local_l = 0;
            for (l, nl) in around[..=k].iter().enumerate() {
                let dl = if K > 0 { K } else { reduced.dim[nl.block] };
                let block = blocks[next];
                next += 1;
                let w = &self.w_local[local_l..local_l + dl * d];
                local_l += dl * d;
                match dense_n {
                    // Dense S: a diagonal block may be written whole (the upper half is unread).
                    Some(n) if D > 0 && K == CAMERA => {
                        subtract_product::<D, CAMERA>(&mut self.s_values[block..], n, y, w)
                    }
                    _ => {
                        let diagonal = k == l;
                        for q in 0..dl {
                            let first = if diagonal { q } else { 0 };
                            let start = match dense_n {
                                Some(n) => block + q * n + first,
                                None => reduced.value_index(block, diagonal, first, q),
                            };
                            let column = &mut self.s_values[start..start + dk - first];
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
            }
            local_k += dk * d;
        }
        debug_assert_eq!(local_k, local);
        Ok(())
    }

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
        match &mut self.backend {
            Backend::Dense { mem } => {
                let x = MatMut::from_column_major_slice_mut(&mut self.rhs, n, 1);
                dense_llt_solve::solve_in_place_with_conj(
                    MatRef::from_column_major_slice(&self.s_values, n, n),
                    Conj::No,
                    x,
                    Par::Seq,
                    MemStack::new(mem),
                );
            }
            Backend::Sparse(chol) => chol.solve_in_place(&mut self.rhs),
        }
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

/// Which compiled kernel serves eliminated block `e`: (point, all cameras) or the general one.
#[inline(always)]
fn kernel_of(solver: &SchurSolver, e: usize) -> (usize, bool) {
    (solver.dim[e], solver.camera_neighbours[e])
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

/// Eliminates every block of `solver` into S; errs at the first V that is not positive definite.
#[inline(always)]
fn eliminate_all(
    solver: &mut SchurSolver,
    full: &BlockPattern,
    values: &[f64],
    shift: Option<&[f64]>,
) -> Result<(), NotPositiveDefinite> {
    for e in 0..solver.eliminated {
        let result = match kernel_of(solver, e) {
            (3, true) => solver.eliminate::<3, CAMERA>(e, full, values, shift),
            (3, false) => solver.eliminate::<3, 0>(e, full, values, shift),
            _ => solver.eliminate::<0, 0>(e, full, values, shift),
        };
        result.map_err(|i| NotPositiveDefinite {
            row: solver.offset[e] + i,
        })?;
    }
    Ok(())
}

#[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma"))]
fn eliminate_all_wide(
    solver: &mut SchurSolver,
    full: &BlockPattern,
    values: &[f64],
    shift: Option<&[f64]>,
) -> Result<(), NotPositiveDefinite> {
    eliminate_all(solver, full, values, shift)
}

/// The block size the fixed-size kernel is compiled for: a BAL camera.
const CAMERA: usize = 9;

/// `S[.., ..] −= Y Wᵀ` for column-major `y`, `w` (K × D) into the K×K block of a column-major
/// matrix with leading dimension `n` that starts at `s[0]`.
#[inline(always)]
fn subtract_product<const D: usize, const K: usize>(s: &mut [f64], n: usize, y: &[f64], w: &[f64]) {
    let (y, w) = (&y[..K * D], &w[..K * D]);
    for q in 0..K {
        let column = &mut s[q * n..q * n + K];
        let mut acc = [0.0; K];
        for t in 0..D {
            let factor = w[t * K + q];
            for r in 0..K {
                acc[r] += y[t * K + r] * factor;
            }
        }
        for r in 0..K {
            column[r] -= acc[r];
        }
    }
}

/// In-place Cholesky of the d×d row-major matrix `a` (lower triangle read and written).
/// On failure returns the row of the non-positive pivot.
#[inline(always)]
fn small_cholesky(a: &mut [f64], d: usize) -> Result<(), usize> {
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
fn small_cholesky_inverse(a: &mut [f64], d: usize) {
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

#[cfg(test)]
mod tests {
    use nalgebra::{DMatrix, Vector2, Vector3};

    use super::*;
    use crate::factors::testing::Rng;
    use crate::factors::{BetweenSe2, PriorSe2, ReprojectionSnavely};
    use crate::geometry::{Point3, Se2, SnavelyCamera};
    use crate::problem::{Gauge, Key, Problem};
    use crate::solver::linearize::{linearize, Scratch, SystemLayout};

    /// A small BA: cameras looking at a cloud of points, observations with pixel noise, every
    /// point seen by 2–4 cameras; cameras and points then perturbed.
    fn synthetic_bundle_adjustment(cameras: usize, points: usize, seed: u64) -> Problem {
        let mut rng = Rng::new(seed);
        let mut problem = Problem::with_gauge(Gauge::Free).eliminating(&["point3"]);
        let mut truth = Vec::new();
        for i in 0..cameras {
            let p = [
                0.1 * rng.normal(),
                0.1 * rng.normal(),
                0.1 * rng.normal(),
                rng.normal(),
                rng.normal(),
                -20.0 + rng.normal(),
                500.0 + 10.0 * rng.normal(),
                1e-3 * rng.normal(),
                1e-5 * rng.normal(),
            ];
            let camera = SnavelyCamera::from_bal(&p);
            truth.push(camera);
            let mut noisy = p;
            for v in noisy.iter_mut().take(6) {
                *v += 0.01 * rng.normal();
            }
            problem
                .add_variable(i as Key, Box::new(SnavelyCamera::from_bal(&noisy)))
                .unwrap();
        }
        let unit = DMatrix::identity(2, 2);
        for j in 0..points {
            let x = Vector3::new(3.0 * rng.normal(), 3.0 * rng.normal(), 3.0 * rng.normal());
            let key = (cameras + j) as Key;
            let noisy = x + 0.05 * Vector3::new(rng.normal(), rng.normal(), rng.normal());
            problem.add_variable(key, Box::new(Point3(noisy))).unwrap();
            let seen = 2 + (rng.next_u64() % 3) as usize;
            let first = (rng.next_u64() as usize) % cameras;
            for k in 0..seen.min(cameras) {
                let i = (first + k) % cameras;
                let z = truth[i].project(&x) + Vector2::new(rng.normal(), rng.normal());
                let factor = ReprojectionSnavely::new(i as Key, key, z);
                problem
                    .add_factor(Box::new(factor), &unit, None, "obs")
                    .unwrap();
            }
        }
        problem
    }

    /// The damped step (H + diag(shift))⁻¹ b through `solver`, and through a sparse Cholesky of
    /// the same system in the same layout.
    fn steps(problem: &Problem, choice: LinearSolverChoice) -> (Vec<f64>, Vec<f64>, bool) {
        let fixed = vec![false; problem.values.len()];
        let plan = plan(
            problem.factors(),
            &problem.values,
            &fixed,
            &problem.eliminate,
            choice,
        )
        .expect("something to eliminate");
        let layout =
            SystemLayout::with_ordering(problem.factors(), &problem.values, &fixed, &plan.ordering);
        let mut scratch = Scratch::new(&layout);
        let mut h = vec![0.0; layout.pattern.nnz()];
        let mut b = vec![0.0; layout.n()];
        linearize(
            problem.factors(),
            &problem.values,
            &layout,
            &mut scratch,
            &mut h,
            &mut b,
        )
        .unwrap();
        let pattern = &layout.pattern;
        let shift: Vec<f64> = (0..pattern.n)
            .map(|c| 1e-3 * h[pattern.diagonal_index(c)].max(1e-6))
            .collect();
        let mut schur = SchurSolver::new(pattern, &plan).unwrap();
        schur.factorize(pattern, &h, Some(&shift)).unwrap();
        let mut x = b.clone();
        schur.solve_in_place(&mut x);

        let mut damped = h.clone();
        for (c, s) in shift.iter().enumerate() {
            damped[pattern.diagonal_index(c)] += s;
        }
        let mut chol =
            SparseCholesky::analyze(pattern, SupernodalThreshold::FORCE_SUPERNODAL).unwrap();
        chol.factorize(pattern, &damped).unwrap();
        let mut reference = b;
        chol.solve_in_place(&mut reference);
        (x, reference, schur.is_dense())
    }

    fn assert_close(x: &[f64], reference: &[f64]) {
        let scale = reference.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for (a, b) in x.iter().zip(reference) {
            assert!((a - b).abs() <= 1e-8 * scale, "{a} vs {b} (scale {scale})");
        }
    }

    #[test]
    fn dense_and_sparse_schur_steps_match_sparse_cholesky() {
        let problem = synthetic_bundle_adjustment(7, 80, 3);
        for (choice, dense) in [
            (LinearSolverChoice::DenseSchur, true),
            (LinearSolverChoice::SparseSchur, false),
            (LinearSolverChoice::Auto, true),
        ] {
            let (x, reference, was_dense) = steps(&problem, choice);
            assert_eq!(was_dense, dense, "{choice:?}");
            assert_close(&x, &reference);
        }
    }

    /// Nothing about the mechanism is specific to BA: eliminate poses of a 2D pose graph. The
    /// chosen poses never share a factor (a chain: every other one), and the step is exact.
    #[test]
    fn eliminates_any_kind_keeping_v_block_diagonal() {
        let mut rng = Rng::new(9);
        let mut problem = Problem::new().eliminating(&["se2"]);
        let n = 30;
        for i in 0..n {
            let guess = Se2::new(i as f64 + 0.1 * rng.normal(), 0.1 * rng.normal(), 0.0);
            problem.add_variable(i, Box::new(guess)).unwrap();
        }
        let information = DMatrix::identity(3, 3);
        problem
            .add_factor(
                Box::new(PriorSe2::new(0, Se2::new(0.0, 0.0, 0.0))),
                &information,
                None,
                "prior",
            )
            .unwrap();
        for i in 0..n - 1 {
            let step = Se2::new(1.0, 0.05 * rng.normal(), 0.02 * rng.normal());
            let factor = BetweenSe2::new(i, i + 1, step);
            problem
                .add_factor(Box::new(factor), &information, None, "odometry")
                .unwrap();
        }
        let loop_closure = BetweenSe2::new(0, n - 1, Se2::new((n - 1) as f64, 0.0, 0.0));
        problem
            .add_factor(Box::new(loop_closure), &information, None, "loop")
            .unwrap();
        let fixed = vec![false; n as usize];
        let planned = plan(
            problem.factors(),
            &problem.values,
            &fixed,
            &problem.eliminate,
            LinearSolverChoice::SparseSchur,
        )
        .unwrap();
        assert!(planned.eliminated >= 10 && planned.eliminated <= 15);
        let (x, reference, _) = steps(&problem, LinearSolverChoice::SparseSchur);
        assert_close(&x, &reference);
    }

    #[test]
    fn every_linear_solver_reaches_the_same_optimum() {
        use crate::solver::{optimize, SolverOptions};
        let mut costs = Vec::new();
        for choice in [
            LinearSolverChoice::SparseCholesky,
            LinearSolverChoice::DenseSchur,
            LinearSolverChoice::SparseSchur,
        ] {
            let mut problem = synthetic_bundle_adjustment(6, 60, 11);
            let options = SolverOptions {
                linear_solver: choice,
                function_tolerance: 1e-12,
                ..SolverOptions::bundle_adjustment()
            };
            let summary = optimize(&mut problem, &options, &mut |_| {
                std::ops::ControlFlow::Continue(())
            })
            .unwrap();
            assert!(summary.converged, "{choice:?}: {:?}", summary.termination);
            assert_eq!(
                summary.used.schur.is_some(),
                choice != LinearSolverChoice::SparseCholesky
            );
            costs.push(summary.final_chi2);
        }
        for c in &costs {
            assert!((c - costs[0]).abs() <= 1e-6 * costs[0], "{costs:?}");
        }
    }

    #[test]
    fn an_indefinite_point_block_is_reported_at_its_rows() {
        // A point nobody observes: its V block is zero.
        let mut problem = synthetic_bundle_adjustment(3, 5, 4);
        let key = 100;
        problem
            .add_variable(key, Box::new(Point3(Vector3::new(0.0, 0.0, 0.0))))
            .unwrap();
        let fixed = vec![false; problem.values.len()];
        let planned = plan(
            problem.factors(),
            &problem.values,
            &fixed,
            &problem.eliminate,
            LinearSolverChoice::Auto,
        )
        .unwrap();
        let layout = SystemLayout::with_ordering(
            problem.factors(),
            &problem.values,
            &fixed,
            &planned.ordering,
        );
        let mut scratch = Scratch::new(&layout);
        let mut h = vec![0.0; layout.pattern.nnz()];
        let mut b = vec![0.0; layout.n()];
        linearize(
            problem.factors(),
            &problem.values,
            &layout,
            &mut scratch,
            &mut h,
            &mut b,
        )
        .unwrap();
        let mut schur = SchurSolver::new(&layout.pattern, &planned).unwrap();
        let error = schur.factorize(&layout.pattern, &h, None).unwrap_err();
        assert_eq!(layout.key_at_row(&problem.values, error.row), key);
    }
}
