//! What the optimiser did: per-iteration reports and a final Summary in the spirit of Ceres',
//! and its assembly from a finished iteration loop (`Run`) plus what only the caller knows
//! (`Context`).

use std::borrow::Borrow;
use std::time::Instant;

use serde::Serialize;

use super::linear::SchurReport;
use super::linearize::SystemLayout;
use super::options::SolverOptions;
use crate::problem::FactorEntry;
use crate::problem::{Key, Values};

#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct IterationReport {
    pub iteration: usize,
    /// chi2 after this iteration (the trial chi2 when the step was rejected is in `trial_chi2`).
    pub chi2: f64,
    pub trial_chi2: f64,
    pub relative_decrease: f64,
    pub gradient_max_norm: f64,
    /// ‖Δx‖∞ of the step (tried, whether or not accepted).
    pub step_norm: f64,
    /// ‖Δx‖₂ of the step, the norm Ceres reports as `|step|` (0 for incremental updates, which
    /// do not measure it).
    pub step_two_norm: f64,
    /// Actual over predicted decrease of the cost (Ceres' `tr_ratio`); 0 when the step could not
    /// be computed, and for incremental updates.
    pub gain_ratio: f64,
    #[schema(required = true)]
    pub lambda: Option<f64>,
    #[schema(required = true)]
    pub trust_radius: Option<f64>,
    pub accepted: bool,
    pub linearize_seconds: f64,
    pub factorize_seconds: f64,
    pub solve_seconds: f64,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum TerminationReason {
    FunctionTolerance,
    GradientTolerance,
    ParameterTolerance,
    MaxIterations,
    /// LM's λ or Dogleg's radius ran out of range without an acceptable step.
    NoProgress,
    /// Nothing to optimise (no free variables or no factors).
    Trivial,
    /// The caller stopped the solve (cancelled, preempted or shut down).
    Interrupted,
}

#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct Termination {
    pub reason: TerminationReason,
    /// The measured value that triggered it, and the threshold it crossed.
    pub value: f64,
    pub threshold: f64,
    pub message: String,
}

impl Termination {
    pub fn converged(&self) -> bool {
        !matches!(
            self.reason,
            TerminationReason::MaxIterations
                | TerminationReason::NoProgress
                | TerminationReason::Interrupted
        )
    }
}

#[derive(Clone, Debug, Default, Serialize, utoipa::ToSchema)]
pub struct Timings {
    pub preprocess_seconds: f64,
    pub initialization_seconds: f64,
    pub linearize_seconds: f64,
    pub factorize_seconds: f64,
    pub linear_solve_seconds: f64,
    pub evaluate_seconds: f64,
}

/// What was actually used, next to what was given.
#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct UsedOptions {
    pub method: String,
    pub linear_solver: String,
    pub factorization: String,
    pub ordering: String,
    pub threads: usize,
    pub initialization: String,
    /// Variables fixed automatically to remove gauge freedom (one per unanchored component).
    pub gauge_fixed: Vec<Key>,
    /// Present when landmark-like variables were eliminated by Schur complement.
    #[serde(skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<Object>)]
    pub schur: Option<SchurReport>,
    /// For a session's local re-solve: how many variables the region let move (the rest of the
    /// problem held fixed).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub region_variables: Option<usize>,
    /// For a session's incremental update (`solver::incremental`): what it relinearised,
    /// reordered and refactored, and the time of each phase (iSAM2's `ISAM2Result`).
    #[serde(skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<Object>)]
    pub incremental: Option<super::incremental::UpdateReport>,
}

#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct Summary {
    pub method: String,
    pub given_options: SolverOptions,
    pub used: UsedOptions,
    pub num_variables: usize,
    pub num_free_variables: usize,
    pub num_factors: usize,
    pub num_residuals: usize,
    pub num_parameters: usize,
    pub jacobian_nnz_blocks: usize,
    pub hessian_nnz: usize,
    pub factor_nnz: usize,
    /// chi2 = Σ ρ(eᵀΩe) of the given initial values.
    pub initial_chi2: f64,
    /// chi2 after initialisation, where one ran.
    #[schema(required = true)]
    pub initialized_chi2: Option<f64>,
    pub final_chi2: f64,
    pub iterations: usize,
    pub successful_steps: usize,
    pub unsuccessful_steps: usize,
    pub termination: Termination,
    pub converged: bool,
    /// Wall time of the optimisation itself (preprocessing, initialisation and iterations).
    pub solve_seconds: f64,
    pub timings: Timings,
    pub iteration_log: Vec<IterationReport>,
}

impl Summary {
    /// A multi-line human report, like Ceres' FullReport.
    pub fn report(&self) -> String {
        let t = &self.timings;
        let mut s = String::new();
        use std::fmt::Write;
        let _ = writeln!(s, "factord solver summary");
        let _ = writeln!(s, "{:<28}{:>20}{:>24}", "", "given", "used");
        let _ = writeln!(
            s,
            "{:<28}{:>20}{:>24}",
            "method",
            self.given_options.method.name(),
            self.used.method
        );
        let _ = writeln!(
            s,
            "{:<28}{:>20}{:>24}",
            "initialization",
            format!("{:?}", self.given_options.initialization).to_lowercase(),
            self.used.initialization
        );
        let _ = writeln!(
            s,
            "{:<28}{:>20}{:>24}",
            "linear solver", "", self.used.linear_solver
        );
        let _ = writeln!(
            s,
            "{:<28}{:>20}{:>24}",
            "factorization", "", self.used.factorization
        );
        let _ = writeln!(s, "{:<28}{:>20}{:>24}", "ordering", "", self.used.ordering);
        let _ = writeln!(s, "{:<28}{:>20}{:>24}", "threads", "", self.used.threads);
        if !self.used.gauge_fixed.is_empty() {
            let _ = writeln!(
                s,
                "gauge: no anchor given, fixed variable(s) {:?}",
                self.used.gauge_fixed
            );
        }
        let _ = writeln!(
            s,
            "variables {} ({} free, {} parameters), factors {} ({} residuals)",
            self.num_variables,
            self.num_free_variables,
            self.num_parameters,
            self.num_factors,
            self.num_residuals
        );
        let _ = writeln!(
            s,
            "H nnz (lower) {}, L nnz {}",
            self.hessian_nnz, self.factor_nnz
        );
        let _ = writeln!(s, "initial chi2 {:.6e}", self.initial_chi2);
        if let Some(c) = self.initialized_chi2 {
            let _ = writeln!(s, "after init   {c:.6e}");
        }
        let _ = writeln!(s, "final chi2   {:.6e}", self.final_chi2);
        let _ = writeln!(
            s,
            "iterations {} ({} successful, {} unsuccessful)",
            self.iterations, self.successful_steps, self.unsuccessful_steps
        );
        let _ = writeln!(
            s,
            "time (s): total {:.6}  preprocess {:.6}  init {:.6}  linearize {:.6}  factorize {:.6}  solve {:.6}  evaluate {:.6}",
            self.solve_seconds,
            t.preprocess_seconds,
            t.initialization_seconds,
            t.linearize_seconds,
            t.factorize_seconds,
            t.linear_solve_seconds,
            t.evaluate_seconds
        );
        let _ = writeln!(s, "termination: {}", self.termination.message);
        s
    }
}

/// What a finished iteration loop hands back.
pub(super) struct Run {
    pub chi2: f64,
    pub termination: Termination,
    pub log: Vec<IterationReport>,
    pub timings: Timings,
    pub factorization: &'static str,
    pub factor_nnz: usize,
    pub linear_solver: String,
    pub ordering: &'static str,
    pub schur: Option<SchurReport>,
}

/// Facts about the solve that the iteration loop does not know.
pub(super) struct Context {
    pub start: Instant,
    pub initialization: String,
    pub gauge_fixed: Vec<Key>,
    pub initial_chi2: f64,
    pub initialized_chi2: Option<f64>,
    pub region: Option<usize>,
}

impl Run {
    pub(super) fn summary<E: Borrow<FactorEntry> + Sync>(
        self,
        options: &SolverOptions,
        layout: &SystemLayout,
        factors: &[E],
        values: &Values,
        context: Context,
    ) -> Summary {
        let successful = self.log.iter().filter(|r| r.accepted).count();
        let iterations = self.log.len();
        Summary {
            method: options.method.name().into(),
            given_options: options.clone(),
            used: UsedOptions {
                method: options.method.name().into(),
                linear_solver: self.linear_solver,
                factorization: self.factorization.into(),
                ordering: self.ordering.into(),
                threads: layout.threads(),
                initialization: context.initialization,
                gauge_fixed: context.gauge_fixed,
                schur: self.schur,
                region_variables: context.region,
                incremental: None,
            },
            num_variables: values.len(),
            num_free_variables: layout.var_at.len(),
            num_factors: factors.len(),
            num_residuals: factors
                .iter()
                .map(|f| f.borrow().factor.residual_dim())
                .sum(),
            num_parameters: layout.n(),
            jacobian_nnz_blocks: factors.iter().map(|f| f.borrow().factor.keys().len()).sum(),
            hessian_nnz: layout.pattern.nnz(),
            factor_nnz: self.factor_nnz,
            initial_chi2: context.initial_chi2,
            initialized_chi2: context.initialized_chi2,
            final_chi2: self.chi2,
            iterations,
            successful_steps: successful,
            unsuccessful_steps: iterations - successful,
            converged: self.termination.converged(),
            termination: self.termination,
            solve_seconds: context.start.elapsed().as_secs_f64(),
            timings: self.timings,
            iteration_log: self.log,
        }
    }
}

/// A χ² obtained by subtraction (a model's `rᵀr − yᵀy`, a total less a decrease), which is never
/// negative in exact arithmetic: round-off below zero at an exact optimum (a published
/// `-7.006e-46`) is 0. NaN stays NaN: it reports a real failure.
pub fn non_negative_chi2(chi2: f64) -> f64 {
    if chi2 < 0.0 {
        0.0
    } else {
        chi2
    }
}

#[cfg(test)]
mod tests {
    use super::non_negative_chi2;

    #[test]
    fn round_off_below_zero_is_zero_and_nan_stays() {
        assert_eq!(non_negative_chi2(1e-30 - (1e-30 + 1e-45)), 0.0);
        assert_eq!(non_negative_chi2(-7.006e-46), 0.0);
        assert_eq!(non_negative_chi2(2.0), 2.0);
        assert!(non_negative_chi2(f64::NAN).is_nan());
    }
}
