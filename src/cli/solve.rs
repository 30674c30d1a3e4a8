//! `factord solve`: optimise a pose graph file and write the result, its Summary and plots.

use std::path::PathBuf;
use std::time::Instant;

use factord::factors::RobustKernel;
use factord::io::{self, Dimension};
use factord::solver::{self, Initialization, Method, SolverOptions};

use super::progress::Progress;
use super::solve_output::{print_iteration, write_summary_json};
use super::value_parsers::{parse_init, parse_method, parse_robust};
use super::CliError;

#[derive(clap::Args)]
pub struct SolveArgs {
    /// Graph file (g2o or TORO), or the vertices file of a pair.
    graph: PathBuf,
    /// Edges file, when vertices and edges are in two files (course `-v.dat` / `-e.dat`).
    #[arg(long)]
    edges: Option<PathBuf>,
    /// gn | lm | dogleg
    #[arg(long, default_value = "gn", value_parser = parse_method)]
    method: Method,
    #[arg(long, default_value_t = 100)]
    max_iterations: usize,
    /// none | chordal | auto (chordal when it lowers the initial chi2)
    #[arg(long, default_value = "auto", value_parser = parse_init)]
    init: Initialization,
    /// Robust kernel on every factor, e.g. huber:1.0 or cauchy:0.5
    #[arg(long, value_parser = parse_robust)]
    robust: Option<RobustKernel>,
    #[arg(long, default_value_t = 1e-6)]
    function_tolerance: f64,
    /// Write the optimised graph (g2o format).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Write the optimised trajectory in TUM format.
    #[arg(long)]
    tum: Option<PathBuf>,
    /// Write the Summary as JSON.
    #[arg(long)]
    summary_json: Option<PathBuf>,
    /// Draw the initial guess, the optimum, its loop closures and the convergence plot as SVG
    /// (3D graphs from above).
    #[arg(long)]
    plot: Option<PathBuf>,
    /// Solve this many times from the same initial values (as the reference benchmarks do, in
    /// one process); the Summary's `solve_seconds` is then the median, all runs are in
    /// `solve_seconds_runs`.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
    repeat: u32,
    /// Print only errors.
    #[arg(long)]
    quiet: bool,
}

pub fn run(args: SolveArgs) -> Result<(), CliError> {
    let load_start = Instant::now();
    let loading = Progress::loading(&args.graph, args.quiet);
    let graph = io::load(&args.graph, args.edges.as_deref());
    loading.finish();
    let mut graph = graph?;
    let load_seconds = load_start.elapsed().as_secs_f64();
    if args.robust.is_some() {
        graph.problem.set_robust_kernel(args.robust);
    }
    let options = SolverOptions {
        method: args.method,
        max_iterations: args.max_iterations,
        initialization: args.init,
        function_tolerance: args.function_tolerance,
        ..SolverOptions::default()
    };
    if !args.quiet {
        println!(
            "loaded {} ({} variables, {} factors) in {:.3}s",
            args.graph.display(),
            graph.problem.values.len(),
            graph.problem.factors().len(),
            load_seconds
        );
    }
    let quiet = args.quiet;
    let initial = graph.problem.values.clone();
    let mut runs = Vec::with_capacity(args.repeat as usize);
    let mut summary = None;
    for run in 0..args.repeat {
        graph.problem.values.clone_from(&initial);
        let last = run + 1 == args.repeat;
        let progress = Progress::solving(options.max_iterations, quiet || !last);
        let s = solver::optimize(&mut graph.problem, &options, &mut |r| {
            progress.iteration(r);
            if !quiet && last {
                progress.suspend(|| print_iteration(r));
            }
            std::ops::ControlFlow::Continue(())
        });
        progress.finish();
        let s = s?;
        runs.push(s.solve_seconds);
        summary = Some(s);
    }
    let mut summary = summary.expect("--repeat is at least 1, so there was a run");
    runs.sort_by(f64::total_cmp);
    summary.solve_seconds = runs[runs.len() / 2];
    if !quiet {
        print!("{}", summary.report());
    }
    if let Some(path) = &args.summary_json {
        let mut extra = vec![
            ("input", args.graph.display().to_string().into()),
            ("load_seconds", load_seconds.into()),
            ("solve_seconds_runs", runs.clone().into()),
        ];
        if graph.dimension == Dimension::Three {
            let g2o = io::g2o::chi2_g2o_convention(graph.problem.factors(), &graph.problem.values);
            extra.push(("final_chi2_g2o", g2o.into()));
        }
        write_summary_json(path, &summary, extra)?;
    }
    if let Some(path) = &args.out {
        io::g2o::write(&graph, path)?;
    }
    if let Some(path) = &args.tum {
        io::tum::write(&graph, path)?;
    }
    if let Some(path) = &args.plot {
        let title = format!(
            "{}: {} variables, {} factors",
            args.graph.file_name().unwrap_or_default().to_string_lossy(),
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
        io::svg::write(path, &svg)?;
    }
    Ok(())
}
