//! What the batch solvers (`solve`, `ba`, `direct-ba`) print and write about a solve: one line an
//! iteration (χ² lines, or Ceres' rows for `ba`), and the Summary as JSON with command-specific
//! fields added.

use factord::problem::Problem;
use factord::solver::{self, IterationReport, SolverOptions, Summary};

use super::ceres_style::CeresRows;
use super::progress::Progress;
use super::stdio::{Console, OutputArg};
use super::CliError;

/// How iterations are printed.
pub enum IterationLines {
    /// χ², relative decrease, damping and phase times (pose-graph users, g2o's χ² convention).
    Chi2,
    /// Ceres' rows, starting from a point of this χ² (bundle adjustment users).
    Ceres { initial_chi2: f64 },
}

/// Optimises, printing each iteration on `console`.
pub fn optimize_verbose(
    problem: &mut Problem,
    options: &SolverOptions,
    console: Console,
    lines: IterationLines,
) -> Result<Summary, CliError> {
    let progress = Progress::solving(options.max_iterations, console.quiet());
    let mut ceres = match lines {
        IterationLines::Ceres { initial_chi2 } => Some(CeresRows::new(options, initial_chi2)),
        IterationLines::Chi2 => None,
    };
    let summary = solver::optimize(problem, options, &mut |r| {
        progress.iteration(r);
        let text = match &mut ceres {
            Some(rows) => rows.rows(r),
            None => chi2_line(r),
        };
        progress.suspend(|| console.print(&text));
        std::ops::ControlFlow::Continue(())
    });
    progress.finish();
    Ok(summary?)
}

/// The Summary as pretty JSON with `extra` fields added at its top level.
pub fn summary_json(
    summary: &Summary,
    extra: Vec<(&str, serde_json::Value)>,
) -> Result<String, CliError> {
    let mut json = serde_json::to_value(summary)?;
    let map = json
        .as_object_mut()
        .expect("Summary serialises as an object");
    for (key, value) in extra {
        map.insert(key.into(), value);
    }
    Ok(serde_json::to_string_pretty(&json)? + "\n")
}

/// Writes [`summary_json`] to `--summary-json`.
pub fn write_summary_json(
    target: &OutputArg,
    summary: &Summary,
    extra: Vec<(&str, serde_json::Value)>,
) -> Result<(), CliError> {
    target.write("--summary-json", summary_json(summary, extra)?.as_bytes())
}

pub fn chi2_line(r: &IterationReport) -> String {
    let damping = match (r.lambda, r.trust_radius) {
        (Some(l), _) => format!("lambda {l:9.3e}"),
        (_, Some(t)) => format!("radius {t:9.3e}"),
        _ => " ".repeat(16),
    };
    format!(
        "iter {:3}  chi2 {:14.6e}  rel.decr {:10.3e}  |g|inf {:9.3e}  |dx|inf {:9.3e}  {damping}  {}  lin {:.2}ms fact {:.2}ms solve {:.2}ms\n",
        r.iteration,
        r.chi2,
        r.relative_decrease,
        r.gradient_max_norm,
        r.step_norm,
        if r.accepted { "accepted" } else { "rejected" },
        r.linearize_seconds * 1e3,
        r.factorize_seconds * 1e3,
        r.solve_seconds * 1e3,
    )
}
