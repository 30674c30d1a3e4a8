//! Flag syntaxes shared by the batch solvers (clap value parsers; clap prints their message and
//! exits with 2).

use factord::factors::RobustKernel;
use factord::solver::{Initialization, LinearSolverChoice, Method};

pub fn parse_method(s: &str) -> Result<Method, String> {
    Method::parse(s).ok_or_else(|| format!("unknown method `{s}` (gn, lm, dogleg)"))
}

pub fn parse_gnc_kernel(s: &str) -> Result<factord::solver::GncKernel, String> {
    factord::solver::GncKernel::parse(s)
        .ok_or_else(|| format!("unknown graduated non-convexity kernel `{s}` (tls, gm)"))
}

pub fn parse_init(s: &str) -> Result<Initialization, String> {
    match s {
        "none" => Ok(Initialization::None),
        "chordal" => Ok(Initialization::Chordal),
        "auto" => Ok(Initialization::Auto),
        _ => Err(format!(
            "unknown initialisation `{s}` (none, chordal, auto)"
        )),
    }
}

pub fn parse_robust(s: &str) -> Result<RobustKernel, String> {
    RobustKernel::parse(s).map_err(|e| e.to_string())
}

pub fn parse_linear_solver(s: &str) -> Result<LinearSolverChoice, String> {
    LinearSolverChoice::parse(s).ok_or_else(|| {
        format!("unknown linear solver `{s}` (auto, sparse_cholesky, dense_schur, sparse_schur, iterative_schur)")
    })
}

/// `--threads`: 0 (one per core) up to [`factord::solver::MAX_THREADS`].
pub fn parse_threads(s: &str) -> Result<usize, String> {
    let max = factord::solver::MAX_THREADS;
    match s.parse::<usize>() {
        Ok(n) if n <= max => Ok(n),
        _ => Err(format!("`{s}`: expected 0 (one per core) to {max}")),
    }
}
