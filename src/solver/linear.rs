//! The linear solver an iteration loop factorises with: sparse Cholesky of the whole system, or
//! the Schur complement of its landmark-like variables.

use std::ops::ControlFlow;

use serde::Serialize;

use super::budget::Budget;
use super::cholesky::{NotPositiveDefinite, SparseCholesky};
use super::schur::{ImplicitSchur, SchurSolver};
use super::structure::BlockPattern;
use super::supernodes::BlockSupernodes;

/// One solver per solve, so the variants' sizes do not matter.
#[derive(Debug)]
#[allow(clippy::large_enum_variant)]
pub enum LinearSolver {
    Sparse(SparseCholesky),
    Schur(SchurSolver),
    ImplicitSchur(ImplicitSchur),
}

/// What the Schur complement did, for the Summary.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct SchurReport {
    pub eliminated_variables: usize,
    pub reduced_variables: usize,
    /// Scalar unknowns of the reduced system S.
    pub reduced_dimension: usize,
    /// `"dense"` or `"sparse"`: how S was factorised; `"implicit"`: S was never formed.
    pub reduced_factorization: &'static str,
    /// Why S was not formed (implicit only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub implicit_reason: Option<String>,
    /// Conjugate-gradient iterations over the solve, and the most one step took (implicit only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cg_iterations: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cg_max_iterations_per_step: Option<usize>,
}

impl LinearSolver {
    /// Factorises the matrix with lower triangle `values` in `pattern`'s layout. `Break`:
    /// `budget` stopped the Schur complement's elimination or refused its reduced factorisation
    /// (a sparse Cholesky is one call, checked by the caller before it starts).
    pub fn factorize(
        &mut self,
        pattern: &BlockPattern,
        values: &[f64],
        budget: &dyn Budget,
    ) -> Result<ControlFlow<()>, NotPositiveDefinite> {
        match self {
            Self::Sparse(chol) => chol.factorize(pattern, values).map(ControlFlow::Continue),
            Self::Schur(schur) => schur.factorize_within(pattern, values, None, budget),
            Self::ImplicitSchur(schur) => schur.factorize_within(pattern, values, None, budget),
        }
    }

    /// A chi2 decrease too small to matter to the solve (only an iterative solver uses it: see
    /// [`ImplicitSchur::set_negligible_decrease`]).
    pub fn set_negligible_decrease(&mut self, chi2_decrease: f64) {
        if let Self::ImplicitSchur(schur) = self {
            schur.set_negligible_decrease(chi2_decrease);
        }
    }

    /// Whether [`LinearSolver::factorize_shifted`] works without a damped copy of the matrix.
    pub fn shifts_in_place(&self) -> bool {
        matches!(self, Self::Schur(_) | Self::ImplicitSchur(_))
    }

    /// Factorises `values + diag(shift)` for a solver that [`LinearSolver::shifts_in_place`];
    /// `budget` as in [`LinearSolver::factorize`].
    pub fn factorize_shifted(
        &mut self,
        pattern: &BlockPattern,
        values: &[f64],
        shift: &[f64],
        budget: &dyn Budget,
    ) -> Result<ControlFlow<()>, NotPositiveDefinite> {
        match self {
            Self::Sparse(_) => unreachable!("sparse Cholesky factorises a damped copy"),
            Self::Schur(schur) => schur.factorize_within(pattern, values, Some(shift), budget),
            Self::ImplicitSchur(schur) => {
                schur.factorize_within(pattern, values, Some(shift), budget)
            }
        }
    }

    /// Solves with the last factorisation of `values` (the unshifted H the Schur complement
    /// eliminated; a sparse Cholesky reads only its factor).
    pub fn solve_in_place(&mut self, pattern: &BlockPattern, values: &[f64], rhs: &mut [f64]) {
        match self {
            Self::Sparse(chol) => chol.solve_in_place(rhs),
            Self::Schur(schur) => schur.solve_in_place(pattern, values, rhs),
            Self::ImplicitSchur(schur) => schur.solve_in_place(pattern, values, rhs),
        }
    }

    /// What solves, and whose code factorises (our loops or faer's).
    pub fn label(&self) -> String {
        match self {
            Self::Sparse(chol) => format!("sparse Cholesky ({})", chol.implementation()),
            Self::Schur(s) => match s.sparse_factor() {
                Some(chol) => format!(
                    "Schur complement, sparse Cholesky ({}) of the reduced system",
                    chol.implementation()
                ),
                None => "Schur complement, dense Cholesky (faer) of the reduced system".into(),
            },
            Self::ImplicitSchur(s) => format!(
                "implicit Schur complement, conjugate gradients preconditioned by Schur-Jacobi ({})",
                s.reason()
            ),
        }
    }

    /// "supernodal", "simplicial" or "dense": the factorisation of the system actually factorised.
    pub fn factorization(&self) -> &'static str {
        match self {
            Self::Sparse(chol) => chol.kind(),
            Self::Schur(s) => s.sparse_factor().map_or("dense", SparseCholesky::kind),
            Self::ImplicitSchur(_) => "none (conjugate gradients)",
        }
    }

    /// Floating-point operations of one factorisation, when known before it runs (the Schur
    /// complement predicts and checks its reduced factorisation itself, after the elimination).
    pub fn factor_flops(&self) -> Option<f64> {
        match self {
            Self::Sparse(chol) => Some(chol.factor_flops()),
            Self::Schur(_) | Self::ImplicitSchur(_) => None,
        }
    }

    /// Bytes the factorisation holds (the Schur complement's reduced system counted as its
    /// factor's nonzeros).
    pub fn numeric_bytes(&self) -> u64 {
        match self {
            Self::Sparse(chol) => chol.numeric_bytes(),
            Self::Schur(s) => 8 * s.factor_nnz() as u64,
            Self::ImplicitSchur(s) => 8 * s.numeric_len() as u64,
        }
    }

    /// The solve's supernodes in blocks, when its factor was analysed that way (the chordal
    /// start reuses them).
    pub fn block_supernodes(&self) -> Option<&BlockSupernodes> {
        match self {
            Self::Sparse(chol) => chol.block_supernodes(),
            Self::Schur(_) | Self::ImplicitSchur(_) => None,
        }
    }

    pub fn factor_nnz(&self) -> usize {
        match self {
            Self::Sparse(chol) => chol.factor_nnz(),
            Self::Schur(s) => s.factor_nnz(),
            Self::ImplicitSchur(_) => 0,
        }
    }

    pub fn ordering(&self) -> &'static str {
        match self {
            Self::Sparse(_) => "AMD on the variable graph",
            Self::Schur(s) if s.is_dense() => "eliminated variables first, then the rest as given",
            Self::Schur(_) => "eliminated variables first, then AMD on the reduced graph",
            Self::ImplicitSchur(_) => "eliminated variables first, then the rest as given",
        }
    }

    pub fn schur_report(&self) -> Option<SchurReport> {
        match self {
            Self::Sparse(_) => None,
            Self::Schur(s) => Some(SchurReport {
                eliminated_variables: s.eliminated_blocks(),
                reduced_variables: s.reduced_blocks(),
                reduced_dimension: s.reduced_dim(),
                reduced_factorization: if s.is_dense() { "dense" } else { "sparse" },
                implicit_reason: None,
                cg_iterations: None,
                cg_max_iterations_per_step: None,
            }),
            Self::ImplicitSchur(s) => Some(SchurReport {
                eliminated_variables: s.eliminated_blocks(),
                reduced_variables: s.reduced_blocks(),
                reduced_dimension: s.reduced_dim(),
                reduced_factorization: "implicit",
                implicit_reason: Some(s.reason().to_string()),
                cg_iterations: Some(s.stats().iterations),
                cg_max_iterations_per_step: Some(s.stats().max_iterations),
            }),
        }
    }
}
