//! The sparse nonlinear least-squares solver: layout, linearisation, sparse Cholesky, GN / LM /
//! Dogleg, initialisation and the Summary. Nothing here knows about files or networks.
//!
//! Layer 4: imports `geometry`, `factors`, `problem` and `wire_number` (its options are a wire
//! type); never `io` or anything above.

pub mod budget;
pub mod chi_square;
pub mod cholesky;
mod damping;
mod dogleg;
pub mod gauge;
mod gauss_newton;
pub mod gnc;
mod huge_pages;
pub mod incremental;
pub mod initialize;
mod iterations;
pub mod linear;
pub mod linearize;
pub mod marginals;
mod optimizer;
pub mod options;
mod parts;
pub mod retriangulate;
pub mod schur;
pub(crate) mod simd;
mod stopping;
mod strategy;
pub mod structure;
pub mod summary;
mod supernodal_factor;
mod supernodal_solve;
pub mod supernodes;
pub mod union_find;
pub mod vector;
mod warm;

pub use budget::{Budget, Unlimited};
pub use gnc::{optimize_gnc, GncKernel, GncOptions, GncReport};
pub use optimizer::{optimize, optimize_warm, optimize_warm_within, optimize_within};
pub use options::{Initialization, LinearSolverChoice, Method, SolverOptions, MAX_THREADS};
pub use summary::{IterationReport, Summary, Termination, TerminationReason};
pub use warm::{newton_decrement, optimize_region, optimize_region_within, OrderingCache};

use crate::factors::EvaluationError;
pub use crate::problem::evaluate_chi2;
use crate::problem::{evaluate_chi2_checked, FactorEntry, Key, Values};
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
    /// Refused before any numeric work: the symbolic factorisation says the solve would need
    /// more memory than its budget allows.
    #[error("the solve would need about {estimated} bytes ({} MiB) of memory, more than the limit of {limit} bytes ({} MiB): the graph's factorisation has {factor_nnz} nonzeros", estimated / (1 << 20), limit / (1 << 20))]
    MemoryLimit {
        estimated: u64,
        limit: u64,
        factor_nnz: usize,
    },
    /// The budget (a cancellation, a shutdown) stopped the solve while it evaluated the cost at
    /// the given values, before any step: there is no Summary to give, and nothing changed.
    #[error("interrupted by the solve's budget (cancellation or shutdown) while evaluating the initial cost; the values are unchanged")]
    Interrupted,
    #[error("internal error: {0}")]
    Internal(String),
}

/// [`evaluate_chi2`] that checks `budget` every [`budget::FACTORS_PER_CHECK`] factors.
pub fn evaluate_chi2_within<E: Borrow<FactorEntry> + Sync>(
    factors: &[E],
    values: &Values,
    budget: &dyn Budget,
) -> Result<std::ops::ControlFlow<(), f64>, EvaluationError> {
    evaluate_chi2_checked(factors, values, |k| {
        if k % budget::FACTORS_PER_CHECK == budget::FACTORS_PER_CHECK - 1 {
            budget.checkpoint()
        } else {
            std::ops::ControlFlow::Continue(())
        }
    })
}

/// [`evaluate_chi2_within`] on up to `threads` threads: the factors cut into that many equal
/// runs, each summed on its own thread, the sums added in run order (so a result differs from
/// one thread's only by rounding). The calling thread checks `budget`; the others stop with it.
pub(crate) fn evaluate_chi2_threads<E: Borrow<FactorEntry> + Sync>(
    factors: &[E],
    values: &Values,
    budget: &dyn Budget,
    threads: usize,
) -> Result<std::ops::ControlFlow<(), f64>, EvaluationError> {
    use std::ops::ControlFlow;
    use std::sync::atomic::{AtomicBool, Ordering};
    if threads < 2 || factors.len() < 2 * threads {
        return evaluate_chi2_within(factors, values, budget);
    }
    let stop = AtomicBool::new(false);
    let due = |k: usize| k % budget::FACTORS_PER_CHECK == budget::FACTORS_PER_CHECK - 1;
    let mut runs = factors.chunks(factors.len().div_ceil(threads));
    let first = runs.next().expect("at least two factors");
    let results = std::thread::scope(|s| {
        let others: Vec<_> = runs
            .map(|run| {
                let stop = &stop;
                s.spawn(move || {
                    evaluate_chi2_checked(run, values, |k| {
                        if due(k) && stop.load(Ordering::Relaxed) {
                            ControlFlow::Break(())
                        } else {
                            ControlFlow::Continue(())
                        }
                    })
                })
            })
            .collect();
        let mine = evaluate_chi2_checked(first, values, |k| {
            if due(k) && budget.checkpoint().is_break() {
                stop.store(true, Ordering::Relaxed);
                return ControlFlow::Break(());
            }
            ControlFlow::Continue(())
        });
        parts::mine_then_joined(mine, others)
    });
    parts::sum_of_parts(results)
}
