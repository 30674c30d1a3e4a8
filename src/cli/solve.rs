//! `factord solve`: optimise a pose graph file and write the result, its Summary and plots.

use std::time::Instant;

use factord::factors::RobustKernel;
use factord::io::{self, Dimension};
use factord::solver::gnc::{loop_closures, GncKernel, GncOptions, GncReport};
use factord::solver::{self, Initialization, Method, SolverOptions, Unlimited};

use super::plot::{self, PlotFormat};
use super::progress::Progress;
use super::robots_report::{self, robot_views};
use super::solve_output::{chi2_line, write_summary_json};
use super::stdio::{one_stdin, Console, InputArg, OutputArg};
use super::value_parsers::{parse_gnc_kernel, parse_init, parse_method, parse_robust};
use super::CliError;

/// What `factord solve` does about possibly wrong loop closures.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Outliers {
    Auto,
    Off,
}

#[derive(clap::Args)]
pub struct SolveArgs {
    /// Graph file (g2o or TORO), or the vertices file of a pair; `-` reads standard input. A
    /// relative path not found here is looked up under $FACTORD_DATA.
    graph: InputArg,
    /// Edges file, when vertices and edges are in two files (course `-v.dat` / `-e.dat`).
    #[arg(long)]
    edges: Option<InputArg>,
    /// Solver: gn (Gauss-Newton) | lm (Levenberg-Marquardt) | dogleg (Powell's dogleg)
    #[arg(long, default_value = "gn", value_parser = parse_method)]
    method: Method,
    /// Stop after this many iterations (the solve then reports it did not converge)
    #[arg(long, default_value_t = 100)]
    max_iterations: usize,
    /// none | chordal | auto (chordal when it lowers the initial chi2)
    #[arg(long, default_value = "auto", value_parser = parse_init)]
    init: Initialization,
    /// Robust kernel on every factor, e.g. huber:1.0 or cauchy:0.5 (turns --outliers off)
    #[arg(long, value_parser = parse_robust)]
    robust: Option<RobustKernel>,
    /// Wrong loop closures. auto: every loop closure (a factor between poses whose ids are not
    /// consecutive) may be wrong; those that do not fit the least-squares optimum are rejected
    /// by graduated non-convexity, thresholds from the χ² distribution (no scale to choose).
    /// off: plain least squares (the default: on clean files whose noise is larger than their
    /// information says, e.g. M3500b/c, sphere_bignoise, auto rejects genuine closures).
    #[arg(long, value_enum, default_value_t = Outliers::Off)]
    outliers: Outliers,
    /// The graduated non-convexity surrogate: tls (truncated least squares) | gm (Geman-McClure)
    #[arg(long, default_value = "tls", value_parser = parse_gnc_kernel)]
    gnc_kernel: GncKernel,
    /// Write --out without the factors rejected as wrong (default: written as comments,
    /// `# rejected: EDGE_…`).
    #[arg(long, requires = "out")]
    drop_rejected: bool,
    /// Stop when an accepted step lowers χ² by less than this fraction of it (0: never)
    #[arg(long, default_value_t = 1e-6)]
    function_tolerance: f64,
    /// Write the optimised graph as g2o whatever the extension (the format that carries values
    /// and every factor we read; landmarks as VERTEX_XY and EDGE_BEARING_RANGE_SE2_XY, so a
    /// solved GTSAM landmark file reads back as the same problem); `-` for standard output.
    #[arg(long)]
    out: Option<OutputArg>,
    /// Write the optimised trajectory in TUM format; `-` for standard output. The first column
    /// is the vertex id (a header line says so) unless --stamps gives times.
    #[arg(long)]
    tum: Option<OutputArg>,
    /// Timestamps for --tum: a file of `id stamp` lines, one per pose.
    #[arg(long, requires = "tum")]
    stamps: Option<InputArg>,
    /// Write the Summary as JSON; `-` for standard output.
    #[arg(long)]
    summary_json: Option<OutputArg>,
    /// Draw the initial guess, the optimum, its loop closures and the convergence plot, with
    /// axes (3D graphs from above and from the side); `-` for standard output.
    #[arg(long)]
    plot: Option<OutputArg>,
    /// svg | png [default: png for a path ending in .png, else svg]
    #[arg(long, value_enum, requires = "plot")]
    plot_format: Option<PlotFormat>,
    /// Solve this many times from the same initial values (as the reference benchmarks do, in
    /// one process); the Summary's `solve_seconds` is then the median, all runs are in
    /// `solve_seconds_runs`.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
    repeat: u32,
    /// Print only errors.
    #[arg(long)]
    quiet: bool,
    /// Threads for linearisation and a Schur complement (1: one thread; 0: one per core). A
    /// pose graph's factors do not split between threads, so it solves on one whatever this
    /// says.
    #[arg(long, default_value_t = 1, value_parser = super::value_parsers::parse_threads)]
    threads: usize,
}

pub fn run(args: SolveArgs) -> Result<(), CliError> {
    one_stdin(&[
        ("graph", Some(&args.graph)),
        ("--edges", args.edges.as_ref()),
        ("--stamps", args.stamps.as_ref()),
    ])?;
    let outputs = [
        ("--out", args.out.as_ref()),
        ("--tum", args.tum.as_ref()),
        ("--summary-json", args.summary_json.as_ref()),
        ("--plot", args.plot.as_ref()),
    ];
    let console = Console::for_outputs(&outputs, args.quiet)?;
    let load_start = Instant::now();
    let name = args.graph.name();
    let loading = Progress::loading(&name, args.quiet);
    let graph = load(&args);
    loading.finish();
    let mut graph = graph?;
    let stamps = match &args.stamps {
        Some(input) => Some(io::tum::parse_stamps(
            &input.name(),
            &input.read_to_string("--stamps")?,
        )?),
        None => None,
    };
    let load_seconds = load_start.elapsed().as_secs_f64();
    if args.robust.is_some() {
        graph.problem.set_robust_kernel(args.robust);
    }
    let options = SolverOptions {
        method: args.method,
        max_iterations: args.max_iterations,
        initialization: args.init,
        function_tolerance: args.function_tolerance,
        threads: args.threads,
        ..SolverOptions::default()
    };
    console.print(&format!(
        "loaded {} ({} variables, {} factors) in {:.3}s\n",
        name.display(),
        graph.problem.values.len(),
        graph.problem.factors().len(),
        load_seconds
    ));
    let initial = graph.problem.values.clone();
    let (summary, runs, gnc_report) = solve_runs(&args, &mut graph, &initial, &options, &console)?;
    console.print(&summary.report());
    if let Some(report) = &gnc_report {
        console.print(&rejection_report(report));
    }
    let robots = robot_views(&initial, &graph.problem.values);
    console.print(&robots_report::report(&robots));
    if let Some(target) = &args.summary_json {
        let mut extra = vec![
            ("input", name.display().to_string().into()),
            ("load_seconds", load_seconds.into()),
            ("solve_seconds_runs", runs.clone().into()),
        ];
        extra.extend(summary_extras(&graph, gnc_report.as_ref(), &robots)?);
        write_summary_json(target, &summary, extra)?;
    }
    if let Some(target) = &args.out {
        write_graph(target, &mut graph, gnc_report.as_ref(), args.drop_rejected)?;
    }
    if let Some(target) = &args.tum {
        let text = match (&stamps, &args.stamps) {
            (Some(stamps), Some(input)) => {
                io::tum::to_string_with_stamps(&graph, stamps, &input.name())?
            }
            _ => io::tum::to_string_with_ids(&graph),
        };
        target.write("--tum", text.as_bytes())?;
    }
    if let Some(target) = &args.plot {
        let title = format!(
            "{}: {} variables, {} factors",
            name.file_name().unwrap_or_default().to_string_lossy(),
            graph.problem.values.len(),
            graph.problem.factors().len()
        );
        let svg = io::svg::before_after(
            &initial,
            &graph.problem.values,
            graph.problem.factors(),
            &summary,
            &title,
        );
        plot::write(target, args.plot_format, &svg)?;
    }
    Ok(())
}

/// What `--summary-json` adds about the solved graph: the g2o-convention χ² of a 3D graph, what
/// graduated non-convexity rejected, each robot of a file of several.
fn summary_extras(
    graph: &io::PoseGraph,
    gnc_report: Option<&GncReport>,
    robots: &[robots_report::RobotView],
) -> Result<Vec<(&'static str, serde_json::Value)>, CliError> {
    let mut extra = Vec::new();
    if graph.dimension == Dimension::Three {
        let g2o = io::g2o::chi2_g2o_convention(graph.problem.factors(), &graph.problem.values);
        extra.push(("final_chi2_g2o", g2o.into()));
    }
    if let Some(report) = gnc_report {
        extra.push(("outliers", serde_json::to_value(report)?));
    }
    if !robots.is_empty() {
        extra.push(("robots", serde_json::to_value(robots)?));
    }
    Ok(extra)
}

/// Solves `--repeat` times from `initial` (the last run prints its iterations): the last
/// run's Summary with the median solve time, every run's time, and what graduated
/// non-convexity rejected (`--outliers auto`, no kernel chosen, a file with loop closures).
fn solve_runs(
    args: &SolveArgs,
    graph: &mut io::PoseGraph,
    initial: &factord::problem::Values,
    options: &SolverOptions,
    console: &Console,
) -> Result<(solver::Summary, Vec<f64>, Option<GncReport>), CliError> {
    let candidates = if args.robust.is_none() && args.outliers == Outliers::Auto {
        Some(loop_closures(&graph.problem)).filter(|c| c.iter().any(|&c| c))
    } else {
        None
    };
    let gnc = GncOptions {
        kernel: args.gnc_kernel,
        ..GncOptions::default()
    };
    let mut gnc_report: Option<GncReport> = None;
    let mut runs = Vec::with_capacity(args.repeat as usize);
    let mut summary = None;
    for run in 0..args.repeat {
        graph.problem.values.clone_from(initial);
        let last = run + 1 == args.repeat;
        let progress = Progress::solving(options.max_iterations, args.quiet || !last);
        let mut on_iteration = |r: &solver::IterationReport| {
            progress.iteration(r);
            if last {
                progress.suspend(|| console.print(&chi2_line(r)));
            }
            std::ops::ControlFlow::Continue(())
        };
        let s = match &candidates {
            Some(candidates) => solver::optimize_gnc(
                &mut graph.problem,
                options,
                &gnc,
                candidates,
                &mut on_iteration,
                &Unlimited,
            )
            .map(|(summary, report)| {
                gnc_report = Some(report);
                summary
            }),
            None => solver::optimize(&mut graph.problem, options, &mut on_iteration),
        };
        progress.finish();
        let s = s?;
        runs.push(s.solve_seconds);
        summary = Some(s);
    }
    let mut summary = summary.expect("--repeat is at least 1, so there was a run");
    let mut sorted = runs.clone();
    sorted.sort_by(f64::total_cmp);
    summary.solve_seconds = sorted[sorted.len() / 2];
    Ok((summary, sorted, gnc_report))
}

/// `--out`: the optimised graph, its rejected loop closures as comments (or dropped).
fn write_graph(
    target: &OutputArg,
    graph: &mut io::PoseGraph,
    report: Option<&GncReport>,
    drop_rejected: bool,
) -> Result<(), CliError> {
    let rejected = report.map_or(&[][..], |r| &r.rejected[..]);
    let text = if drop_rejected {
        let rejected: std::collections::HashSet<usize> = rejected.iter().copied().collect();
        graph.problem.retain_factors(|i| !rejected.contains(&i));
        io::g2o::to_string(graph)
    } else {
        io::g2o::to_string_marking(graph, rejected)
    };
    target.write("--out", text.as_bytes())
}

/// The lines saying which loop closures graduated non-convexity rejected.
fn rejection_report(report: &GncReport) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    if !report.graduated {
        let _ = writeln!(
            s,
            "outliers: all {} loop closures fit the least-squares optimum (χ² {} quantile); none rejected",
            report.candidates, report.confidence
        );
        return s;
    }
    let _ = writeln!(
        s,
        "outliers: {} of {} loop closures rejected by graduated non-convexity ({:?}, χ² {} quantile, {} outer steps, {:.3}s)",
        report.rejected.len(),
        report.candidates,
        report.kernel,
        report.confidence,
        report.outer_iterations,
        report.seconds
    );
    for label in &report.rejected_labels {
        let _ = writeln!(s, "  rejected {label}");
    }
    s
}

fn load(args: &SolveArgs) -> Result<io::PoseGraph, CliError> {
    let text = args.graph.read_to_string("graph")?;
    let edges = match &args.edges {
        Some(input) => Some((input.name(), input.read_to_string("--edges")?)),
        None => None,
    };
    Ok(io::parse_pair(
        (&args.graph.name(), &text),
        edges
            .as_ref()
            .map(|(name, text)| (name.as_path(), text.as_str())),
    )?)
}
