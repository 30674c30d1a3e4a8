//! What the batch solvers (`solve`, `ba`, `direct-ba`) print and write about a solve: one line an
//! iteration on stdout, and the Summary as JSON with command-specific fields added.

use std::path::Path;

use factord::problem::Problem;
use factord::solver::{self, IterationReport, SolverOptions, Summary};

use super::progress::Progress;
use super::CliError;

/// Optimises, printing each iteration unless `quiet`.
pub fn optimize_verbose(
    problem: &mut Problem,
    options: &SolverOptions,
    quiet: bool,
) -> Result<Summary, CliError> {
    let progress = Progress::solving(options.max_iterations, quiet);
    let summary = solver::optimize(problem, options, &mut |r| {
        progress.iteration(r);
        if !quiet {
            progress.suspend(|| print_iteration(r));
        }
        std::ops::ControlFlow::Continue(())
    });
    progress.finish();
    Ok(summary?)
}

/// Writes the Summary as JSON with `extra` fields added at its top level.
pub fn write_summary_json(
    path: &Path,
    summary: &Summary,
    extra: Vec<(&str, serde_json::Value)>,
) -> Result<(), CliError> {
    let mut json = serde_json::to_value(summary)?;
    let map = json
        .as_object_mut()
        .expect("Summary serialises as an object");
    for (key, value) in extra {
        map.insert(key.into(), value);
    }
    let text = serde_json::to_string_pretty(&json)?;
    std::fs::write(path, text).map_err(CliError::file(path))
}

pub fn print_iteration(r: &IterationReport) {
    let damping = match (r.lambda, r.trust_radius) {
        (Some(l), _) => format!("lambda {l:9.3e}"),
        (_, Some(t)) => format!("radius {t:9.3e}"),
        _ => " ".repeat(16),
    };
    println!(
        "iter {:3}  chi2 {:14.6e}  rel.decr {:10.3e}  |g|inf {:9.3e}  |dx|inf {:9.3e}  {damping}  {}  lin {:.2}ms fact {:.2}ms solve {:.2}ms",
        r.iteration,
        r.chi2,
        r.relative_decrease,
        r.gradient_max_norm,
        r.step_norm,
        if r.accepted { "accepted" } else { "rejected" },
        r.linearize_seconds * 1e3,
        r.factorize_seconds * 1e3,
        r.solve_seconds * 1e3,
    );
}
