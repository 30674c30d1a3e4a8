//! `factord ba`: bundle adjustment of a BAL problem, optionally normalised and perturbed as
//! Ceres' `BALProblem` does, with the cost in BAL's ½Σ‖r‖² convention.

use std::time::Instant;

use factord::factors::RobustKernel;
use factord::io;
use factord::solver::{LinearSolverChoice, Method, SolverOptions};

use super::ceres_style;
use super::progress::Progress;
use super::solve_output::{optimize_verbose, write_summary_json, IterationLines};
use super::stdio::{Console, InputArg, OutputArg};
use super::value_parsers::{parse_linear_solver, parse_method, parse_robust, parse_threads};
use super::CliError;

#[derive(clap::Args)]
pub struct BaArgs {
    /// BAL problem file; `-` reads standard input. A relative path not found here is looked up
    /// under $FACTORD_DATA.
    problem: InputArg,
    /// Solver: gn (Gauss-Newton) | lm (Levenberg-Marquardt) | dogleg (Powell's dogleg)
    #[arg(long, default_value = "lm", value_parser = parse_method)]
    method: Method,
    /// Stop after this many iterations (the solve then reports it did not converge)
    #[arg(long, default_value_t = 100)]
    max_iterations: usize,
    /// Stop when an accepted step lowers χ² by less than this fraction of it (0: never)
    #[arg(long, default_value_t = 1e-6)]
    function_tolerance: f64,
    /// auto | sparse_cholesky | dense_schur | sparse_schur | iterative_schur (auto: Schur
    /// complement of the points, dense reduced camera system up to 1000 unknowns, sparse beyond,
    /// implicit (iterative_schur: conjugate gradients, S never formed) when an explicit one would
    /// take more than half the available memory)
    #[arg(long, default_value = "auto", value_parser = parse_linear_solver)]
    linear_solver: LinearSolverChoice,
    /// Robust kernel on every observation, e.g. huber:1.0 (pixels)
    #[arg(long, value_parser = parse_robust)]
    robust: Option<RobustKernel>,
    /// Centre on the median point and scale to a median absolute deviation of 100 (as Ceres).
    #[arg(long)]
    normalize: bool,
    /// Gaussian noise std for rotation (rad, angle-axis), camera centre and points: r,t,p.
    #[arg(long, value_parser = parse_perturb)]
    perturb: Option<[f64; 3]>,
    /// Seed of the perturbation.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Write the Summary (plus initial_cost and final_cost in BAL's ½Σ‖r‖²) as JSON; `-` for
    /// standard output.
    #[arg(long)]
    summary_json: Option<OutputArg>,
    /// Point clouds (points and camera centres) before and after, as PLY; `-` for standard
    /// output.
    #[arg(long)]
    ply_initial: Option<OutputArg>,
    /// The point cloud after the solve, as --ply-initial; `-` for standard output.
    #[arg(long)]
    ply_final: Option<OutputArg>,
    /// Write the optimised problem in BAL format; `-` for standard output.
    #[arg(long)]
    out: Option<OutputArg>,
    /// Print only errors (no Ceres-style iteration rows or report)
    #[arg(long)]
    quiet: bool,
    /// Threads for linearisation and the Schur complement (1: one thread, as Ceres'
    /// benchmarks here; 0: one per core)
    #[arg(long, default_value_t = 1, value_parser = parse_threads)]
    threads: usize,
}

fn parse_perturb(s: &str) -> Result<[f64; 3], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("`{s}`: {e} (expected r,t,p, e.g. 0.1,0.5,0.5)"))?;
    match v[..] {
        [r, t, p] if v.iter().all(|x| x.is_finite() && *x >= 0.0) => Ok([r, t, p]),
        _ => Err(format!("`{s}`: expected three non-negative numbers r,t,p")),
    }
}

pub fn run(args: BaArgs) -> Result<(), CliError> {
    let outputs = [
        ("--summary-json", args.summary_json.as_ref()),
        ("--ply-initial", args.ply_initial.as_ref()),
        ("--ply-final", args.ply_final.as_ref()),
        ("--out", args.out.as_ref()),
    ];
    let console = Console::for_outputs(&outputs, args.quiet)?;
    let start = Instant::now();
    let name = args.problem.name();
    let loading = Progress::loading(&name, args.quiet);
    let bal = args
        .problem
        .read_to_string("problem")
        .and_then(|text| Ok(io::bal::parse(&name, &text)?));
    loading.finish();
    let mut bal = bal?;
    let load_seconds = start.elapsed().as_secs_f64();
    if args.normalize {
        bal.normalize();
    }
    if let Some([r, t, p]) = args.perturb {
        bal.perturb(r, t, p, args.seed);
    }
    if args.robust.is_some() {
        bal.problem.set_robust_kernel(args.robust);
    }
    if let Some(target) = &args.ply_initial {
        let ply = io::ply::to_string(&bal.points(), &bal.camera_centres());
        target.write("--ply-initial", ply.as_bytes())?;
    }
    let initial_cost = bal.cost();
    console.print(&format!(
        "loaded {} ({} cameras, {} points, {} observations) in {load_seconds:.3}s\n",
        name.display(),
        bal.num_cameras,
        bal.num_points,
        bal.problem.factors().len()
    ));
    let options = SolverOptions {
        method: args.method,
        max_iterations: args.max_iterations,
        function_tolerance: args.function_tolerance,
        linear_solver: args.linear_solver,
        threads: args.threads,
        ..SolverOptions::bundle_adjustment()
    };
    let lines = IterationLines::Ceres {
        initial_chi2: 2.0 * initial_cost,
    };
    let summary = optimize_verbose(&mut bal.problem, &options, console, lines)?;
    let final_cost = bal.cost();
    console.print(&ceres_style::summary_report(&summary));
    // Which linear solver ran, and for the implicit Schur complement why (auto chose it) and
    // how many conjugate-gradient iterations it took.
    let cg = summary.used.schur.as_ref().and_then(|s| s.cg_iterations);
    console.print(&match cg {
        Some(cg) => format!(
            "Linear solver: {} ({cg} CG iterations)\n",
            summary.used.linear_solver
        ),
        None => format!("Linear solver: {}\n", summary.used.linear_solver),
    });
    if let Some(target) = &args.summary_json {
        write_summary_json(
            target,
            &summary,
            vec![
                ("input", name.display().to_string().into()),
                ("load_seconds", load_seconds.into()),
                ("initial_cost", initial_cost.into()),
                ("final_cost", final_cost.into()),
            ],
        )?;
    }
    if let Some(target) = &args.ply_final {
        let ply = io::ply::to_string(&bal.points(), &bal.camera_centres());
        target.write("--ply-final", ply.as_bytes())?;
    }
    if let Some(target) = &args.out {
        target.write("--out", io::bal::to_string(&bal).as_bytes())?;
    }
    Ok(())
}
