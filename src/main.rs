//! `factord`: command-line entry point.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use clap::{Parser, Subcommand};

mod cli {
    pub mod progress;
}
use cli::progress::Progress;

use factord::factors::RobustKernel;
use factord::geometry::image::Pinhole;
use factord::io::{self, Dimension};
use factord::server::{self, ServeConfig};
use factord::solver::{
    self, Initialization, IterationReport, LinearSolverChoice, Method, SolverOptions,
};

#[derive(Parser)]
#[command(
    name = "factord",
    version,
    about = "Sparse nonlinear least-squares back-end for pose graphs"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Optimise a pose graph file (g2o, TORO, or a course vertices/edges pair).
    Solve(SolveArgs),
    /// Run the service: HTTP API, zenoh peer, worker pool (see README).
    Serve(ServeArgs),
    /// Bundle adjustment of a BAL problem (optionally normalised and perturbed, as the course).
    Ba(BaArgs),
    /// Direct (photometric) bundle adjustment of the course's images, poses and point patches.
    DirectBa(DirectBaArgs),
    /// The sliding-window fusion experiment on EuRoC: make the inputs, run the window, report APE.
    FusionEval(FusionEvalArgs),
    /// Time the numeric sparse Cholesky of a graph's normal equations at its optimum, and write
    /// the matrix in Matrix Market form for comparison with other libraries.
    BenchCholesky(BenchCholeskyArgs),
}

#[derive(clap::Args)]
struct SolveArgs {
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

#[derive(clap::Args)]
struct BaArgs {
    /// BAL problem file.
    problem: PathBuf,
    /// gn | lm | dogleg
    #[arg(long, default_value = "lm", value_parser = parse_method)]
    method: Method,
    #[arg(long, default_value_t = 100)]
    max_iterations: usize,
    #[arg(long, default_value_t = 1e-6)]
    function_tolerance: f64,
    /// auto | sparse_cholesky | dense_schur | sparse_schur (auto: Schur complement of the
    /// points, dense reduced camera system up to 1000 unknowns)
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
    /// Write the Summary (plus initial_cost and final_cost in BAL's ½Σ‖r‖²) as JSON.
    #[arg(long)]
    summary_json: Option<PathBuf>,
    /// Point clouds (points and camera centres) before and after, as PLY.
    #[arg(long)]
    ply_initial: Option<PathBuf>,
    #[arg(long)]
    ply_final: Option<PathBuf>,
    /// Write the optimised problem in BAL format.
    #[arg(long)]
    out: Option<PathBuf>,
    #[arg(long)]
    quiet: bool,
}

#[derive(clap::Args)]
struct DirectBaArgs {
    /// Directory with poses.txt, points.txt and 0.png, 1.png, …
    dir: PathBuf,
    /// Pinhole intrinsics fx,fy,cx,cy [default: the course's 277.34,291.402,312.234,239.777]
    #[arg(long, value_parser = parse_intrinsics)]
    intrinsics: Option<Pinhole>,
    /// Robust kernel on every patch residual (16 gray levels), e.g. huber:40 or none
    #[arg(long, default_value = "huber:40", value_parser = parse_optional_robust)]
    robust: OptionalRobust,
    #[arg(long, default_value_t = 100)]
    max_iterations: usize,
    #[arg(long, default_value_t = 1e-6)]
    function_tolerance: f64,
    /// Write the Summary plus the per-image patch agreement before and after as JSON.
    #[arg(long)]
    summary_json: Option<PathBuf>,
    /// Points and camera trajectory before and after, as PLY.
    #[arg(long)]
    ply_initial: Option<PathBuf>,
    #[arg(long)]
    ply_final: Option<PathBuf>,
    #[arg(long)]
    quiet: bool,
}

fn parse_intrinsics(s: &str) -> Result<Pinhole, String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("`{s}`: {e} (expected fx,fy,cx,cy)"))?;
    match v[..] {
        [fx, fy, cx, cy] if v.iter().all(|x| x.is_finite()) && fx > 0.0 && fy > 0.0 => {
            Ok(Pinhole { fx, fy, cx, cy })
        }
        _ => Err(format!(
            "`{s}`: expected four finite numbers fx,fy,cx,cy with fx, fy > 0"
        )),
    }
}

/// A robust kernel or `none` (clap reads a bare `Option` field as "flag may be absent").
#[derive(Clone, Copy)]
struct OptionalRobust(Option<RobustKernel>);

fn parse_optional_robust(s: &str) -> Result<OptionalRobust, String> {
    if s == "none" {
        return Ok(OptionalRobust(None));
    }
    parse_robust(s).map(|k| OptionalRobust(Some(k)))
}

fn direct_bundle_adjust(args: DirectBaArgs) -> Result<(), String> {
    let start = Instant::now();
    let camera = args.intrinsics.unwrap_or(io::direct_ba::COURSE_CAMERA);
    let loading = Progress::loading(&args.dir, args.quiet);
    let problem = io::direct_ba::load(&args.dir, camera, args.robust.0).map_err(|e| e.to_string());
    loading.finish();
    let mut problem = problem?;
    let load_seconds = start.elapsed().as_secs_f64();
    let before = problem.agreement();
    if let Some(path) = &args.ply_initial {
        io::ply::write_trajectory(path, &problem.points(), &problem.camera_centres())
            .map_err(|e| e.to_string())?;
    }
    let quiet = args.quiet;
    if !quiet {
        println!(
            "loaded {} ({} images, {} points, {} point-image factors, {} points seen by no image) in {load_seconds:.3}s",
            args.dir.display(),
            problem.num_poses(),
            problem.num_points(),
            problem.problem.factors().len(),
            problem.unseen_points,
        );
    }
    let options = SolverOptions {
        max_iterations: args.max_iterations,
        function_tolerance: args.function_tolerance,
        ..SolverOptions::bundle_adjustment()
    };
    let summary = optimize_verbose(&mut problem.problem, &options, quiet)?;
    let after = problem.agreement();
    if !quiet {
        print!("{}", summary.report());
        println!(
            "cost (Σρ(‖r‖²), gray levels²): {:.6e} -> {:.6e}, {} accepted steps",
            summary.initial_chi2, summary.final_chi2, summary.successful_steps
        );
        println!("mean |patch − image| per image (gray levels), before -> after:");
        for (b, a) in before.iter().zip(&after) {
            println!(
                "  image {}: {:.2} ({} points) -> {:.2} ({} points)",
                b.image,
                b.mean_abs_patch_difference,
                b.points_visible,
                a.mean_abs_patch_difference,
                a.points_visible
            );
        }
    }
    if let Some(path) = &args.summary_json {
        let value = |v: &Vec<io::direct_ba::ImageAgreement>| {
            serde_json::to_value(v).map_err(|e| e.to_string())
        };
        write_summary_json(
            path,
            &summary,
            vec![
                ("input", args.dir.display().to_string().into()),
                ("load_seconds", load_seconds.into()),
                ("agreement_before", value(&before)?),
                ("agreement_after", value(&after)?),
            ],
        )?;
    }
    if let Some(path) = &args.ply_final {
        io::ply::write_trajectory(path, &problem.points(), &problem.camera_centres())
            .map_err(|e| e.to_string())?;
    }
    Ok(())
}

#[derive(clap::Args)]
struct FusionEvalArgs {
    /// EuRoC directory with imu0.csv and the ground truth
    #[arg(long, default_value = "../shared/data/imu/euroc_V1_01_easy")]
    data: PathBuf,
    /// Ground-truth file in that directory (TUM format)
    #[arg(long, default_value = "groundtruth_20hz_tum.txt")]
    truth: String,
    /// Run on these inputs (as written by --inputs-out) instead of making new ones
    #[arg(long)]
    inputs: Option<PathBuf>,
    /// Keyframes in the window
    #[arg(long, default_value_t = 10)]
    window: usize,
    /// Seconds of the sequence to use
    #[arg(long, default_value_t = 140.0)]
    seconds: f64,
    #[arg(long, default_value_t = 2024)]
    seed: u64,
    /// Leave out the IMU (keyframes linked by relative poses and priors only)
    #[arg(long)]
    no_imu: bool,
    /// Leave out the map-matching priors
    #[arg(long)]
    no_priors: bool,
    /// Leave out the lidar relative poses
    #[arg(long)]
    no_relative: bool,
    /// Write the inputs (for GTSAM: benches/fusion/gtsam_fixed_lag.py)
    #[arg(long)]
    inputs_out: Option<PathBuf>,
    /// Write the estimated trajectory (newest state after each keyframe) in TUM format
    #[arg(long)]
    tum_out: Option<PathBuf>,
    /// Print the result as JSON
    #[arg(long)]
    json: bool,
    /// Stream the inputs to a running `factord serve` over zenoh (this endpoint, e.g.
    /// tcp/127.0.0.1:7447) as a robot would, instead of running the window in this process
    #[arg(long)]
    zenoh: Option<String>,
    /// Session name to create on that server
    #[arg(long, default_value = "fusion-eval")]
    session: String,
}

fn fusion_eval(args: FusionEvalArgs) -> Result<(), String> {
    use factord::fusion::experiment::{self, Generation};
    let inputs = match &args.inputs {
        Some(path) => {
            let text =
                std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
            serde_json::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))?
        }
        None => {
            let data = io::euroc::load(&args.data, &args.truth).map_err(|e| e.to_string())?;
            let generation = Generation {
                seconds: args.seconds,
                prior_every: if args.no_priors { 0 } else { 10 },
                use_relative: !args.no_relative,
                use_imu: !args.no_imu,
                window: args.window,
                seed: args.seed,
                ..Generation::default()
            };
            experiment::generate(&data, &generation)?
        }
    };
    if let Some(path) = &args.inputs_out {
        let text = serde_json::to_string(&inputs).map_err(|e| e.to_string())?;
        std::fs::write(path, text).map_err(|e| format!("{}: {e}", path.display()))?;
    }
    let estimates = match &args.zenoh {
        Some(endpoint) => tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .map_err(|e| e.to_string())?
            .block_on(factord::fusion::stream::run_over_zenoh(
                endpoint,
                &args.session,
                &inputs,
            ))?,
        None => experiment::run(&inputs).map_err(|e| e.to_string())?,
    };
    let (full, trans) = experiment::ape(&inputs, &estimates);
    let update = experiment::Percentiles::of(
        &estimates
            .iter()
            .map(|e| e.update_seconds * 1e3)
            .collect::<Vec<_>>(),
    );
    let latency: Option<Vec<f64>> = estimates
        .iter()
        .map(|e| e.latency_seconds.map(|s| s * 1e3))
        .collect();
    if let Some(path) = &args.tum_out {
        std::fs::write(path, experiment::tum(&inputs, &estimates))
            .map_err(|e| format!("{}: {e}", path.display()))?;
    }
    let result = serde_json::json!({
        "generation": inputs.generation,
        "window": inputs.window,
        "use_imu": inputs.use_imu,
        "keyframes": estimates.len(),
        "relative_poses": inputs.relative_poses.len(),
        "pose_priors": inputs.pose_priors.len(),
        "ape_full": full,
        "ape_trans": trans,
        "update_ms": update,
        // Over zenoh: from publishing a keyframe's messages to its state's arrival.
        "latency_ms": latency.map(|l| experiment::Percentiles::of(&l)),
        "through": if args.zenoh.is_some() { "zenoh" } else { "in-process" },
        "iterations_mean": estimates.iter().map(|e| e.iterations as f64).sum::<f64>()
            / estimates.len().max(1) as f64,
    });
    if args.json {
        println!("{result}");
    } else {
        println!(
            "{}",
            serde_json::to_string_pretty(&result).map_err(|e| e.to_string())?
        );
    }
    Ok(())
}

/// Optimises, printing each iteration unless `quiet`.
fn optimize_verbose(
    problem: &mut factord::problem::Problem,
    options: &SolverOptions,
    quiet: bool,
) -> Result<solver::Summary, String> {
    let progress = Progress::solving(options.max_iterations, quiet);
    let summary = solver::optimize(problem, options, &mut |r| {
        progress.iteration(r);
        if !quiet {
            progress.suspend(|| print_iteration(r));
        }
        std::ops::ControlFlow::Continue(())
    });
    progress.finish();
    summary.map_err(|e| e.to_string())
}

/// Writes the Summary as JSON with `extra` fields added at its top level.
fn write_summary_json(
    path: &std::path::Path,
    summary: &solver::Summary,
    extra: Vec<(&str, serde_json::Value)>,
) -> Result<(), String> {
    let mut json = serde_json::to_value(summary).map_err(|e| e.to_string())?;
    let map = json
        .as_object_mut()
        .expect("Summary serialises as an object");
    for (key, value) in extra {
        map.insert(key.into(), value);
    }
    let text = serde_json::to_string_pretty(&json).map_err(|e| e.to_string())?;
    std::fs::write(path, text).map_err(|e| format!("{}: {e}", path.display()))
}

fn parse_fsync(s: &str) -> Result<factord::journal::Fsync, String> {
    match s {
        "always" => Ok(factord::journal::Fsync::Always),
        "interval" => Ok(factord::journal::Fsync::Interval),
        "never" => Ok(factord::journal::Fsync::Never),
        _ => Err(format!("`{s}`: expected always, interval or never")),
    }
}

fn parse_linear_solver(s: &str) -> Result<LinearSolverChoice, String> {
    LinearSolverChoice::parse(s).ok_or_else(|| {
        format!("unknown linear solver `{s}` (auto, sparse_cholesky, dense_schur, sparse_schur)")
    })
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

fn bundle_adjust(args: BaArgs) -> Result<(), String> {
    let start = Instant::now();
    let loading = Progress::loading(&args.problem, args.quiet);
    let bal = io::bal::load(&args.problem).map_err(|e| e.to_string());
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
    if let Some(path) = &args.ply_initial {
        io::ply::write(path, &bal.points(), &bal.camera_centres()).map_err(|e| e.to_string())?;
    }
    let initial_cost = bal.cost();
    if !args.quiet {
        println!(
            "loaded {} ({} cameras, {} points, {} observations) in {load_seconds:.3}s; initial cost {initial_cost:.6e}",
            args.problem.display(),
            bal.num_cameras,
            bal.num_points,
            bal.problem.factors().len()
        );
    }
    let options = SolverOptions {
        method: args.method,
        max_iterations: args.max_iterations,
        function_tolerance: args.function_tolerance,
        linear_solver: args.linear_solver,
        ..SolverOptions::bundle_adjustment()
    };
    let quiet = args.quiet;
    let summary = optimize_verbose(&mut bal.problem, &options, quiet)?;
    let final_cost = bal.cost();
    if !quiet {
        print!("{}", summary.report());
        println!("cost (½Σ‖r‖²): {initial_cost:.6e} -> {final_cost:.6e}");
    }
    if let Some(path) = &args.summary_json {
        write_summary_json(
            path,
            &summary,
            vec![
                ("input", args.problem.display().to_string().into()),
                ("load_seconds", load_seconds.into()),
                ("initial_cost", initial_cost.into()),
                ("final_cost", final_cost.into()),
            ],
        )?;
    }
    if let Some(path) = &args.ply_final {
        io::ply::write(path, &bal.points(), &bal.camera_centres()).map_err(|e| e.to_string())?;
    }
    if let Some(path) = &args.out {
        io::bal::write(&bal, path).map_err(|e| e.to_string())?;
    }
    Ok(())
}

/// Settings come from defaults, then `--config`, then `FACTORD_*` environment variables, then
/// flags.
#[derive(clap::Args)]
struct ServeArgs {
    /// JSON config file (the fields of `ServeConfig`, see README).
    #[arg(long, env = "FACTORD_CONFIG")]
    config: Option<PathBuf>,
    /// HTTP address [default: 127.0.0.1:8080]
    #[arg(long, env = "FACTORD_LISTEN")]
    listen: Option<String>,
    /// State directory [default: ./factord-state]
    #[arg(long, env = "FACTORD_STATE_DIR")]
    state_dir: Option<PathBuf>,
    /// zenoh endpoints to listen on (repeatable) [default: tcp/127.0.0.1:7447]
    #[arg(long, env = "FACTORD_ZENOH_LISTEN", value_delimiter = ',')]
    zenoh_listen: Option<Vec<String>>,
    /// zenoh routers or peers to connect to (repeatable)
    #[arg(long, env = "FACTORD_ZENOH_CONNECT", value_delimiter = ',')]
    zenoh_connect: Option<Vec<String>>,
    /// Multicast scouting: on | off [default: off]
    #[arg(long, env = "FACTORD_ZENOH_MULTICAST", value_parser = parse_on_off)]
    zenoh_multicast: Option<bool>,
    /// A zenoh JSON5 configuration to start from (access control, TLS endpoints); the
    /// --zenoh-* settings apply on top of it.
    #[arg(long, env = "FACTORD_ZENOH_CONFIG")]
    zenoh_config: Option<PathBuf>,
    /// The token label every zenoh peer acts as (needs zenoh's own authentication in
    /// --zenoh-config: user/password, or mutual TLS); without it and with tokens on, zenoh
    /// peers reach only unowned sessions.
    #[arg(long, env = "FACTORD_ZENOH_PRINCIPAL")]
    zenoh_principal: Option<String>,
    /// Do not start the zenoh peer (HTTP only).
    #[arg(long, env = "FACTORD_NO_ZENOH")]
    no_zenoh: bool,
    /// When journal appends reach the disk: always (fsync before every acknowledgement) |
    /// interval (fsync in the background every journal.interval_ms) | never [default: always]
    #[arg(long, env = "FACTORD_FSYNC", value_parser = parse_fsync)]
    fsync: Option<factord::journal::Fsync>,
    /// Bearer tokens for HTTP, `label token` or `token` per line (FACTORD_TOKENS adds
    /// comma-separated ones); required automatically when --listen is beyond loopback.
    #[arg(long, env = "FACTORD_TOKENS_FILE")]
    tokens_file: Option<PathBuf>,
    /// Keep sessions in memory only (no journal, nothing recovered at start).
    #[arg(long, env = "FACTORD_NO_JOURNAL")]
    no_journal: bool,
    /// Solver worker threads [default: number of cores]
    #[arg(long, env = "FACTORD_WORKERS")]
    workers: Option<usize>,
    /// Largest request body in bytes [default: 268435456]
    #[arg(long, env = "FACTORD_MAX_BODY_BYTES")]
    max_body_bytes: Option<usize>,
    /// Log filter level: error | warn | info | debug | trace [default: info]
    #[arg(long, env = "FACTORD_LOG", default_value = "info")]
    log: tracing::Level,
}

fn parse_on_off(s: &str) -> Result<bool, String> {
    match s {
        "on" | "true" | "1" => Ok(true),
        "off" | "false" | "0" => Ok(false),
        _ => Err(format!("expected on or off, got `{s}`")),
    }
}

fn serve(args: ServeArgs) -> Result<(), String> {
    tracing_subscriber::fmt()
        .with_max_level(args.log)
        .with_writer(std::io::stderr)
        .init();
    let mut config = match &args.config {
        Some(path) => ServeConfig::from_file(path).map_err(|e| e.to_string())?,
        None => ServeConfig::default(),
    };
    if let Some(v) = args.listen {
        config.listen = v;
    }
    if let Some(v) = args.state_dir {
        config.state_dir = v;
    }
    if let Some(v) = args.zenoh_listen {
        config.zenoh.listen = v;
    }
    if let Some(v) = args.zenoh_connect {
        config.zenoh.connect = v;
    }
    if let Some(v) = args.zenoh_multicast {
        config.zenoh.multicast = v;
    }
    if args.no_zenoh {
        config.zenoh_enabled = false;
    }
    if let Some(v) = args.zenoh_config {
        config.zenoh.config_file = Some(v);
    }
    if let Some(v) = args.zenoh_principal {
        config.zenoh.principal = Some(v);
    }
    if let Some(v) = args.workers {
        config.limits.workers = v.max(1);
    }
    if let Some(v) = args.max_body_bytes {
        config.max_body_bytes = v;
    }
    if let Some(v) = args.fsync {
        config.journal.fsync = v;
    }
    if args.no_journal {
        config.journal.enabled = false;
    }
    if let Some(v) = args.tokens_file {
        config.auth.tokens_file = Some(v);
    }
    // zenoh needs the multi-threaded runtime.
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(|e| e.to_string())?;
    runtime
        .block_on(server::run(config, server::shutdown_signal()))
        .map_err(|e| e.to_string())
}

#[derive(clap::Args)]
struct BenchCholeskyArgs {
    graph: PathBuf,
    #[arg(long)]
    edges: Option<PathBuf>,
    #[arg(long, default_value_t = 50)]
    repeat: usize,
    /// Matrix Market output of H (lower triangle, symmetric).
    #[arg(long)]
    write_mtx: Option<PathBuf>,
}

fn parse_method(s: &str) -> Result<Method, String> {
    Method::parse(s).ok_or_else(|| format!("unknown method `{s}` (gn, lm, dogleg)"))
}

fn parse_init(s: &str) -> Result<Initialization, String> {
    match s {
        "none" => Ok(Initialization::None),
        "chordal" => Ok(Initialization::Chordal),
        "auto" => Ok(Initialization::Auto),
        _ => Err(format!(
            "unknown initialisation `{s}` (none, chordal, auto)"
        )),
    }
}

fn parse_robust(s: &str) -> Result<RobustKernel, String> {
    RobustKernel::parse(s).map_err(|e| e.to_string())
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    if !matches!(cli.command, Command::Serve(_)) {
        // Batch commands piped into `head` should stop quietly when the reader goes away, as
        // Unix tools do, not panic on the failed write. The server keeps Rust's default
        // (SIGPIPE ignored) so a client hanging up never kills it.
        // SAFETY: called before any other thread exists; SIG_DFL is a valid disposition.
        unsafe {
            libc::signal(libc::SIGPIPE, libc::SIG_DFL);
        }
    }
    let result = match cli.command {
        Command::Solve(args) => solve(args),
        Command::Serve(args) => serve(args),
        Command::Ba(args) => bundle_adjust(args),
        Command::DirectBa(args) => direct_bundle_adjust(args),
        Command::FusionEval(args) => fusion_eval(args),
        Command::BenchCholesky(args) => factord::solver::cholesky_bench::run(
            &args.graph,
            args.edges.as_deref(),
            args.repeat,
            args.write_mtx.as_deref(),
        )
        .map(|report| println!("{report}"))
        .map_err(|e| e.to_string()),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("error: {message}");
            ExitCode::from(2)
        }
    }
}

fn print_iteration(r: &IterationReport) {
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

fn solve(args: SolveArgs) -> Result<(), String> {
    let load_start = Instant::now();
    let loading = Progress::loading(&args.graph, args.quiet);
    let graph = io::load(&args.graph, args.edges.as_deref()).map_err(|e| e.to_string());
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
        let s = s.map_err(|e| e.to_string())?;
        runs.push(s.solve_seconds);
        summary = Some(s);
    }
    let mut summary = summary.expect("at least one run");
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
        io::g2o::write(&graph, path).map_err(|e| e.to_string())?;
    }
    if let Some(path) = &args.tum {
        io::tum::write(&graph, path).map_err(|e| e.to_string())?;
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
        io::svg::write(path, &svg).map_err(|e| e.to_string())?;
    }
    Ok(())
}
