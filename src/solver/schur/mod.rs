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
//!
//! The files, one concept each:
//! - `plan`: which blocks are eliminated and the reduced system's graph and order ([`SchurPlan`]);
//! - `layout`: where every piece lives — V⁻¹, the S block of every neighbour pair, the U
//!   entries copied into S ([`SchurSolver::new`]);
//! - `eliminate`: one factorisation: U into S, then every eliminated block's V⁻¹ and
//!   S −= Y Wᵀ, with the small fixed-size kernels it uses;
//! - `avx512`: that update for a point and two BAL cameras on 512-bit vectors, where the CPU
//!   has them (dense S, and the sparse S's blocks);
//! - `reduced`: the reduced system S itself, dense or sparse: its factorisation, its solve and
//!   their predicted cost;
//! - `back_substitute`: one solve: the reduced right-hand side, S's solve, and Δe from Δr;
//! - `threads`: the elimination and back-substitution cut into parts for more than one thread;
//! - `choice`: whether S may be formed (explicit) or is too big and only multiplied (implicit);
//! - `implicit`: the implicit Schur complement, S's products and the step by conjugate gradients
//!   ([`ImplicitSchur`]), with `schur_jacobi` (its preconditioner), `pcg` (the iteration) and
//!   `implicit_threads` (its passes cut into parts for more than one thread).
//!
//! This file holds the solver's state, shared by all of them.

mod avx512;
mod back_substitute;
mod choice;
mod eliminate;
mod implicit;
#[cfg(test)]
mod implicit_tests;
mod implicit_threads;
mod layout;
mod pcg;
mod plan;
mod reduced;
mod schur_jacobi;
#[cfg(test)]
mod tests;
mod threads;

use super::budget::FactorCost;
use super::cholesky::SparseCholesky;
use super::structure::BlockPattern;

pub use choice::explicit_limit;
pub(in crate::solver) use eliminate::small_cholesky;
pub use implicit::{CgStats, ImplicitSchur};
pub use plan::{plan, SchurPlan};
use reduced::Backend;

/// One neighbour (reduced block) of an eliminated block: its W block in the full pattern.
#[derive(Debug, Clone, Copy)]
struct Neighbour {
    /// Reduced block number (full position − eliminated).
    block: usize,
    w_pair: usize,
}

/// The block size the fixed-size kernels are compiled for: a BAL camera.
const CAMERA: usize = 9;

/// The elimination checks its budget every this many eliminated blocks: 1024 BAL points seen by
/// four cameras each take about 5 ms (200k points: ~1 s per factorisation), the same grain as
/// linearisation's [`super::budget::FACTORS_PER_CHECK`].
const ELIMINATED_PER_CHECK: usize = 1024;

/// The eliminated blocks as both Schur solvers (explicit and implicit) lay them out: per block
/// its dimension, first row, where its V⁻¹ starts, and its neighbours
/// (`neighbours[neighbour_start[e]..neighbour_start[e + 1]]`, sorted by position).
#[derive(Debug)]
struct EliminatedBlocks {
    /// Scalar rows of the eliminated part; reduced scalar row `i` is full row `rows + i`.
    rows: usize,
    dim: Vec<usize>,
    offset: Vec<usize>,
    /// `ne + 1` entries: the last is V⁻¹'s whole length.
    v_start: Vec<usize>,
    neighbour_start: Vec<usize>,
    neighbours: Vec<Neighbour>,
    /// Per block: whether every neighbour is [`CAMERA`]-sized, so the fixed-size kernels apply.
    camera_neighbours: Vec<bool>,
}

impl EliminatedBlocks {
    /// The first `ne` blocks of `full` (laid out with the plan's ordering).
    fn of(full: &BlockPattern, ne: usize) -> Self {
        let rows = full.offset.get(ne).copied().unwrap_or(full.n);
        let (mut dim, mut offset) = (Vec::with_capacity(ne), Vec::with_capacity(ne));
        let (mut v_start, mut neighbour_start) = (vec![0], vec![0]);
        let mut neighbours = Vec::new();
        for e in 0..ne {
            let d = full.dim[e];
            dim.push(d);
            offset.push(full.offset[e]);
            v_start.push(v_start[e] + d * d);
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
                });
            }
            neighbour_start.push(neighbours.len());
        }
        let camera_neighbours = neighbour_start
            .windows(2)
            .map(|range| {
                neighbours[range[0]..range[1]]
                    .iter()
                    .all(|n| full.dim[ne + n.block] == CAMERA)
            })
            .collect();
        Self {
            rows,
            dim,
            offset,
            v_start,
            neighbour_start,
            neighbours,
            camera_neighbours,
        }
    }

    /// The neighbours of eliminated block `e`.
    fn neighbours_of(&self, e: usize) -> &[Neighbour] {
        &self.neighbours[self.neighbour_start[e]..self.neighbour_start[e + 1]]
    }

    /// Where eliminated block `e`'s V⁻¹ lies in the solver's V⁻¹ array.
    fn v_range(&self, e: usize) -> std::ops::Range<usize> {
        self.v_range_in(e, 0)
    }

    /// [`Self::v_range`] in a part's slice of V⁻¹ that starts at `first`.
    fn v_range_in(&self, e: usize, first: usize) -> std::ops::Range<usize> {
        self.v_start[e] - first..self.v_start[e + 1] - first
    }
}

/// Factorises the normal equations by eliminating a block-diagonal part first; see the module
/// documentation.
pub struct SchurSolver {
    eliminated: usize,
    /// The eliminated blocks' layout: dimensions, rows, where each V⁻¹ starts, neighbours.
    blocks: EliminatedBlocks,
    v_inverse: Vec<f64>,
    /// Per eliminated block, the S block of every neighbour pair (k, l ≤ k), row by row: a pair
    /// of the reduced pattern (sparse) or the index of the block's (0, 0) entry (dense).
    s_block_start: Vec<usize>,
    s_blocks: Vec<usize>,
    /// (full pattern value index, S value index) of every U entry.
    u_map: Vec<(usize, usize)>,
    reduced: BlockPattern,
    s_values: Vec<f64>,
    backend: Backend,
    /// What factorising S costs (predicted from its size or symbolic analysis, timed after each
    /// one), so that a factorisation the budget has no time left for is not started.
    reduced_cost: FactorCost,
    /// W of the current eliminated block's neighbours, and Y = W V⁻¹, each column-major
    /// (dk × d per neighbour, one after the other). Y is not kept past its block: the solve
    /// reads W from H again (Y b = W (V⁻¹ b)), so memory holds W once, in H.
    w_local: Vec<f64>,
    y_local: Vec<f64>,
    rhs: Vec<f64>,
    /// The eliminated blocks of each thread's part (one part: the calling thread alone) and
    /// the buffers of the threads beside the caller's; see `threads`.
    parts: Vec<std::ops::Range<usize>>,
    helpers: Vec<threads::Helper>,
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
    pub fn is_dense(&self) -> bool {
        self.sparse_factor().is_none()
    }

    /// The reduced system's sparse factor, unless it is factorised dense.
    pub fn sparse_factor(&self) -> Option<&SparseCholesky> {
        match &self.backend {
            Backend::Sparse(chol) => Some(chol),
            Backend::Dense { .. } => None,
        }
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
}

/// Which compiled kernel serves eliminated block `e`: (point, all cameras) or the general one.
#[inline(always)]
fn kernel_of(solver: &SchurSolver, e: usize) -> (usize, bool) {
    (solver.blocks.dim[e], solver.blocks.camera_neighbours[e])
}
