//! The reduced camera system S = U − W V⁻¹ Wᵀ once the elimination has filled it: factorised
//! densely (small S: dense kernels beat any sparse bookkeeping) or by the sparse supernodal
//! Cholesky, and solved with that factor.

use dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::{self as dense_llt, LltError, LltRegularization};
use faer::linalg::cholesky::llt::solve as dense_llt_solve;
use faer::sparse::linalg::SupernodalThreshold;
use faer::{Conj, MatMut, MatRef, Par, Spec};

use super::super::cholesky::{NotPositiveDefinite, SparseCholesky, SymbolicError};
use super::super::structure::BlockPattern;

/// One per solver, so the variants' sizes do not matter.
#[allow(clippy::large_enum_variant)]
pub(super) enum Backend {
    /// S is `s_values` as a column-major n×n matrix (lower triangle used).
    Dense { mem: MemBuffer },
    /// S is `s_values` in the reduced [`BlockPattern`]'s layout.
    Sparse(SparseCholesky),
}

impl Backend {
    /// The workspace (dense) or symbolic analysis (sparse) for S with pattern `reduced`.
    pub(super) fn new(reduced: &BlockPattern, dense: bool) -> Result<Self, SymbolicError> {
        Ok(if dense {
            Self::Dense {
                mem: MemBuffer::new(dense_llt::cholesky_in_place_scratch::<f64>(
                    reduced.n,
                    Par::Seq,
                    Spec::default(),
                )),
            }
        } else {
            Self::Sparse(SparseCholesky::analyze(
                reduced,
                SupernodalThreshold::FORCE_SUPERNODAL,
            )?)
        })
    }

    /// Length of S's value array: the whole n×n matrix (dense) or the pattern's lower triangle.
    pub(super) fn values_len(&self, reduced: &BlockPattern) -> usize {
        match self {
            Self::Dense { .. } => reduced.n * reduced.n,
            Self::Sparse(_) => reduced.nnz(),
        }
    }

    /// Floating-point operations of one factorisation of S: n³/3 dense, or from the sparse
    /// symbolic analysis (as the Cholesky path predicts its own).
    pub(super) fn factor_flops(&self, reduced: &BlockPattern) -> f64 {
        match self {
            Self::Dense { .. } => (reduced.n as f64).powi(3) / 3.0,
            Self::Sparse(chol) => chol.factor_flops(),
        }
    }

    /// Factorises S (`s_values`, overwritten by the dense factor); a failing pivot is reported
    /// at its full row, `offset_rows` past the eliminated rows.
    pub(super) fn factorize(
        &mut self,
        reduced: &BlockPattern,
        s_values: &mut [f64],
        offset_rows: usize,
    ) -> Result<(), NotPositiveDefinite> {
        let n = reduced.n;
        match self {
            Self::Dense { mem } => dense_llt::cholesky_in_place(
                MatMut::from_column_major_slice_mut(s_values, n, n),
                LltRegularization::default(),
                Par::Seq,
                MemStack::new(mem),
                Spec::default(),
            )
            .map(|_| ())
            .map_err(|LltError::NonPositivePivot { index }| NotPositiveDefinite {
                row: offset_rows + index,
            }),
            Self::Sparse(chol) => {
                chol.factorize(reduced, s_values)
                    .map_err(|e| NotPositiveDefinite {
                        row: offset_rows + e.row,
                    })
            }
        }
    }

    /// Solves S x = `rhs` in place with the last factorisation of `s_values`.
    pub(super) fn solve_in_place(&mut self, s_values: &[f64], rhs: &mut [f64]) {
        let n = rhs.len();
        match self {
            Self::Dense { mem } => dense_llt_solve::solve_in_place_with_conj(
                MatRef::from_column_major_slice(s_values, n, n),
                Conj::No,
                MatMut::from_column_major_slice_mut(rhs, n, 1),
                Par::Seq,
                MemStack::new(mem),
            ),
            Self::Sparse(chol) => chol.solve_in_place(rhs),
        }
    }
}
