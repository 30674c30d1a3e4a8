//! What the user asks the optimiser for.

use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
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
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
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

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct SolverOptions {
    pub method: Method,
    pub max_iterations: usize,
    /// Stop when an accepted step decreases chi2 by less than this fraction.
    pub function_tolerance: f64,
    /// Stop when ‖Jᵀr‖∞ falls below this.
    pub gradient_tolerance: f64,
    /// Stop when ‖Δx‖∞ falls below this.
    pub parameter_tolerance: f64,
    /// LM damping λ (relative to diag(JᵀJ)) used from the first rejected step on; LM starts
    /// undamped.
    pub initial_lambda: f64,
    /// Initial Dogleg trust-region radius.
    pub initial_trust_radius: f64,
    pub initialization: Initialization,
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
            initial_trust_radius: 1e4,
            initialization: Initialization::Auto,
        }
    }
}
