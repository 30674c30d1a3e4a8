//! An incremental update as a solver [`Summary`], so a session reports it like any solve: the
//! sizes of the problem, the model chi2, the time per phase, and the [`UpdateReport`] in
//! `used.incremental`.

use super::{IncrementalEngine, UpdateReport};
use crate::problem::{Key, Problem};
use crate::solver::summary::{
    IterationReport, Summary, Termination, TerminationReason, Timings, UsedOptions,
};
use crate::solver::SolverOptions;

/// What the caller knows about the update besides its report.
pub struct UpdateContext<'a> {
    pub options: &'a SolverOptions,
    pub gauge: &'a [Key],
    pub initial_chi2: f64,
    pub seconds: f64,
    /// Every step below the threshold that ends a solve: the estimate is the optimum.
    pub converged: bool,
    pub threshold: f64,
}

impl IncrementalEngine {
    /// The update as one Gauss-Newton iteration, for clients that plot convergence.
    pub fn iteration(report: &UpdateReport, initial_chi2: f64) -> IterationReport {
        IterationReport {
            iteration: 1,
            chi2: report.model_chi2,
            trial_chi2: report.model_chi2,
            relative_decrease: if initial_chi2 > 0.0 {
                (initial_chi2 - report.model_chi2) / initial_chi2
            } else {
                0.0
            },
            gradient_max_norm: 0.0,
            step_norm: report.max_delta,
            // Not measured by the incremental engine.
            step_two_norm: 0.0,
            gain_ratio: 0.0,
            lambda: None,
            trust_radius: None,
            accepted: true,
            linearize_seconds: report.linearize_seconds,
            factorize_seconds: report.factorize_seconds,
            solve_seconds: report.solve_seconds,
        }
    }

    pub fn summary(&self, problem: &Problem, report: &UpdateReport, cx: UpdateContext) -> Summary {
        let reason = if cx.converged {
            TerminationReason::ParameterTolerance
        } else {
            TerminationReason::MaxIterations
        };
        Summary {
            method: "incremental Gauss-Newton".into(),
            given_options: cx.options.clone(),
            used: UsedOptions {
                method: "incremental Gauss-Newton (relinearise what moved)".into(),
                linear_solver: "block Cholesky kept between updates".into(),
                factorization: "block left-looking, refactored along touched paths".into(),
                ordering: "AMD of the refactored part, new variables last".into(),
                threads: 1,
                initialization: "none (incremental)".into(),
                gauge_fixed: cx.gauge.to_vec(),
                schur: None,
                region_variables: None,
                incremental: Some(report.clone()),
            },
            num_variables: problem.values.len(),
            num_free_variables: report.columns,
            num_factors: problem.factors().len(),
            num_residuals: self.residuals,
            num_parameters: self.delta.len(),
            jacobian_nnz_blocks: self.jacobian_blocks,
            hessian_nnz: 0,
            factor_nnz: report.factor_nnz,
            initial_chi2: cx.initial_chi2,
            initialized_chi2: None,
            final_chi2: report.model_chi2,
            iterations: report.passes,
            successful_steps: report.passes,
            unsuccessful_steps: 0,
            termination: Termination {
                reason,
                value: report.max_delta,
                threshold: cx.threshold,
                message: format!(
                    "largest step left {:.3e} ({} the threshold {:.1e})",
                    report.max_delta,
                    if cx.converged { "within" } else { "above" },
                    cx.threshold
                ),
            },
            converged: cx.converged,
            solve_seconds: cx.seconds,
            timings: Timings {
                preprocess_seconds: report.order_seconds,
                initialization_seconds: 0.0,
                linearize_seconds: report.linearize_seconds,
                factorize_seconds: report.factorize_seconds,
                linear_solve_seconds: report.solve_seconds,
                evaluate_seconds: 0.0,
            },
            iteration_log: vec![Self::iteration(report, cx.initial_chi2)],
        }
    }
}
