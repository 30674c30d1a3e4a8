//! The sparse nonlinear least-squares solver: layout, linearisation, sparse Cholesky, GN / LM /
//! Dogleg, initialisation and the Summary. Nothing here knows about files or networks.

pub mod cholesky;
pub mod cholesky_bench;
pub mod gauge;
pub mod initialize;
pub mod linear;
pub mod linearize;
pub mod marginals;
mod optimizer;
pub mod options;
pub mod schur;
mod simd;
pub mod structure;
pub mod summary;
mod warm;

pub use optimizer::{optimize, optimize_warm};
pub use options::{Initialization, LinearSolverChoice, Method, SolverOptions};
pub use summary::{IterationReport, Summary, Termination, TerminationReason};
pub use warm::{newton_decrement, optimize_region, OrderingCache};

use crate::factors::{EvaluationError, FactorEntry};
use crate::problem::{Key, Values, Variable};
use std::borrow::Borrow;

#[derive(Debug, thiserror::Error)]
pub enum SolverError {
    /// The normal equations are singular or indefinite at the named variables: they are not
    /// constrained enough (missing measurements, a gauge freedom, or degenerate information).
    #[error("indeterminate system: the linear system is not positive definite at variable(s) {keys:?} (check that these variables are constrained by enough factors)")]
    IndeterminateSystem { keys: Vec<Key> },
    #[error("evaluation failed: {0}")]
    Evaluation(#[from] EvaluationError),
    #[error("the cost became non-finite at iteration {iteration} (Gauss-Newton diverged); try Levenberg-Marquardt")]
    Diverged { iteration: usize },
    #[error("the initial values give a non-finite cost")]
    NonFiniteInitialCost,
    #[error("{0}")]
    Symbolic(#[from] cholesky::SymbolicError),
    #[error("internal error: {0}")]
    Internal(String),
}

/// `Σ ρ(eᵀΩe)` over `factors` at `values`.
pub fn evaluate_chi2<E: Borrow<FactorEntry>>(
    factors: &[E],
    values: &Values,
) -> Result<f64, EvaluationError> {
    let mut total = 0.0;
    let mut e = Vec::new();
    let mut w = Vec::new();
    let mut refs: Vec<&dyn Variable> = Vec::with_capacity(8);
    for f in factors {
        let f = f.borrow();
        refs.clear();
        refs.extend(f.variables().iter().map(|&v| values.variable(v)));
        let d = f.factor.residual_dim();
        e.resize(d, 0.0);
        w.resize(d, 0.0);
        total += f.chi2(&refs, &mut e, &mut w)?;
    }
    Ok(total)
}
