//! What the user asks the optimiser for.

use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Method {
    GaussNewton,
    LevenbergMarquardt,
    Dogleg,
}

impl Method {
    pub fn parse(text: &str) -> Option<Self> {
        match text.to_ascii_lowercase().as_str() {
            "gn" | "gauss_newton" | "gauss-newton" => Some(Self::GaussNewton),
            "lm" | "levenberg_marquardt" | "levenberg-marquardt" => Some(Self::LevenbergMarquardt),
            "dogleg" | "dl" => Some(Self::Dogleg),
            _ => None,
        }
    }
    pub fn name(&self) -> &'static str {
        match self {
            Self::GaussNewton => "gauss_newton",
            Self::LevenbergMarquardt => "levenberg_marquardt",
            Self::Dogleg => "dogleg",
        }
    }
}

/// How the initial estimate is prepared before iterating.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Initialization {
    /// Start from the given values.
    None,
    /// Replace the given values by the chordal-relaxation estimate (pose graphs).
    Chordal,
    /// Compute the chordal estimate and start from it when its chi2 is at least 10× lower than
    /// the given values' (a marginal gain is not worth leaving the basin the given guess is in).
    Auto,
}

/// How the normal equations are solved.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum LinearSolverChoice {
    /// Schur complement when the problem names variables to eliminate (dense reduced system up
    /// to 1000 unknowns, sparse beyond, implicit when an explicit one would not fit in memory
    /// or would fill in to a dense factor predicted slower than conjugate gradients), sparse
    /// Cholesky of the whole system otherwise.
    #[default]
    Auto,
    SparseCholesky,
    DenseSchur,
    SparseSchur,
    /// Schur complement never formed: conjugate gradients on its products, preconditioned by
    /// its block diagonal (Ceres' ITERATIVE_SCHUR with SCHUR_JACOBI). Auto takes it when the
    /// explicit reduced system would not fit in memory, or would be slower (see `Auto`).
    IterativeSchur,
}

impl LinearSolverChoice {
    pub fn parse(text: &str) -> Option<Self> {
        match text.to_ascii_lowercase().replace('-', "_").as_str() {
            "auto" => Some(Self::Auto),
            "sparse_cholesky" | "sparse_normal_cholesky" => Some(Self::SparseCholesky),
            "dense_schur" => Some(Self::DenseSchur),
            "sparse_schur" => Some(Self::SparseSchur),
            "iterative_schur" | "implicit_schur" => Some(Self::IterativeSchur),
            _ => None,
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(default, deny_unknown_fields)]
/// A tolerance of 0 disables its criterion: with all three at 0 a solve runs exactly
/// `max_iterations` iterations (g2o's behaviour), unless LM/Dogleg run out of damping range.
pub struct SolverOptions {
    pub method: Method,
    #[serde(deserialize_with = "crate::wire_number::usize")]
    pub max_iterations: usize,
    /// Stop when an accepted step decreases chi2 by less than this fraction.
    pub function_tolerance: f64,
    /// Stop when ‖Jᵀr‖∞ falls below this.
    pub gradient_tolerance: f64,
    /// Stop when ‖Δx‖∞ falls below this.
    pub parameter_tolerance: f64,
    /// LM damping λ (relative to diag(JᵀJ)) used from the first rejected step on, or from the
    /// start with `damp_first_step`.
    pub initial_lambda: f64,
    /// LM: damp the first step with `initial_lambda` (Ceres' behaviour) instead of trying an
    /// undamped Gauss-Newton step first. A free gauge (bundle adjustment) makes the undamped
    /// system singular, so the undamped attempt there only costs a factorisation.
    pub damp_first_step: bool,
    /// Initial Dogleg trust-region radius.
    pub initial_trust_radius: f64,
    pub initialization: Initialization,
    pub linear_solver: LinearSolverChoice,
    /// Threads one solve may use for linearisation, the trial cost, the Schur complement's
    /// elimination and back-substitution and the implicit Schur complement's products (1: the
    /// calling thread only; 0: one per core). Where the problem's structure does not split
    /// (pose graphs), the solve runs on one thread whatever this says. Results differ from one
    /// thread's by rounding only. In a session the threads beyond the solve's own worker are
    /// borrowed from idle workers of the server's pool (0: as many as the pool has), none while
    /// other work waits.
    #[serde(deserialize_with = "crate::wire_number::usize")]
    pub threads: usize,
}

impl Default for SolverOptions {
    fn default() -> Self {
        Self {
            method: Method::GaussNewton,
            max_iterations: 100,
            function_tolerance: 1e-6,
            gradient_tolerance: 1e-10,
            parameter_tolerance: 1e-10,
            initial_lambda: 1e-4,
            damp_first_step: false,
            initial_trust_radius: 1e4,
            initialization: Initialization::Auto,
            linear_solver: LinearSolverChoice::Auto,
            threads: 1,
        }
    }
}

/// The most threads a solve may ask for.
pub const MAX_THREADS: usize = 256;

impl SolverOptions {
    /// [`SolverOptions::threads`] resolved: 0 is one per core (as the OS reports them).
    pub fn thread_count(&self) -> usize {
        match self.threads {
            0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
            n => n,
        }
    }

    /// Defaults for bundle adjustment: LM damped from the first step (the gauge is free, so
    /// Gauss-Newton's system is singular), no pose-graph initialisation.
    pub fn bundle_adjustment() -> Self {
        Self {
            method: Method::LevenbergMarquardt,
            damp_first_step: true,
            initialization: Initialization::None,
            ..Self::default()
        }
    }

    /// Checks every field's range; on failure names the field and says why.
    pub fn validate(&self) -> Result<(), (&'static str, String)> {
        if self.max_iterations == 0 || self.max_iterations > 100_000 {
            return Err(("max_iterations", "must be between 1 and 100000".into()));
        }
        for (name, value) in [
            ("function_tolerance", self.function_tolerance),
            ("gradient_tolerance", self.gradient_tolerance),
            ("parameter_tolerance", self.parameter_tolerance),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return Err((name, format!("must be a finite number >= 0, got {value}")));
            }
        }
        if self.threads > MAX_THREADS {
            return Err((
                "threads",
                format!(
                    "must be between 0 (one per core) and {MAX_THREADS}, got {}",
                    self.threads
                ),
            ));
        }
        for (name, value) in [
            ("initial_lambda", self.initial_lambda),
            ("initial_trust_radius", self.initial_trust_radius),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return Err((name, format!("must be a finite number > 0, got {value}")));
            }
        }
        Ok(())
    }
}
