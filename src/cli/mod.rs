//! The `factord` command line: the top layer, which may use every library module below it.
//!
//! One file per subcommand (its flags and what it runs); `solve_output` holds what the batch
//! solvers print and write about a solve (`ceres_style` the rows `ba` prints), `value_parsers`
//! the flag syntaxes they share, `stdio` the file arguments where `-` is standard input or output,
//! `data_dir` where datasets are found (`FACTORD_DATA`), `plot` SVG or PNG plots, `error` the one
//! error type every subcommand returns, `logging` the server's log setup.

mod ba;
mod bench_cholesky;
mod ceres_style;
mod data_dir;
mod direct_ba;
mod error;
mod fusion_eval;
mod health;
mod logging;
mod plot;
mod progress;
mod robots_report;
mod serve;
mod solve;
mod solve_output;
mod stdio;
mod value_parsers;

use std::process::ExitCode;

use clap::{Parser, Subcommand};

pub use error::CliError;

#[derive(Parser)]
#[command(
    name = "factord",
    version,
    about = "Sparse nonlinear least-squares back-end for pose graphs"
)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Optimise a pose graph file (g2o, TORO, GTSAM's landmark text, or a TORO vertices/edges pair
    /// such as the ls_slam homework's `-v.dat`/`-e.dat`).
    Solve(solve::SolveArgs),
    /// Run the service: HTTP API, zenoh peer, worker pool (see docs/guide/operations.md).
    Serve(serve::ServeArgs),
    /// Bundle adjustment of a BAL problem (optionally normalised and perturbed as Ceres'
    /// BALProblem does).
    Ba(ba::BaArgs),
    /// Direct (photometric) bundle adjustment of images, poses and point patches (the Shenlan
    /// visual SLAM course's PA7 homework data, $FACTORD_DATA/direct_ba).
    DirectBa(direct_ba::DirectBaArgs),
    /// The sliding-window fusion experiment on EuRoC: make the inputs, run the window, report APE.
    FusionEval(fusion_eval::FusionEvalArgs),
    /// Time the numeric sparse Cholesky of a graph's normal equations at its optimum, and write
    /// the matrix in Matrix Market form for comparison with other libraries.
    BenchCholesky(bench_cholesky::BenchCholeskyArgs),
    /// Ask a running server whether it is healthy (exit 0) or not (exit 1 with the reason).
    Health(health::HealthArgs),
}

/// Exit code of a command that failed after its arguments were accepted (clap also exits with 2
/// on bad arguments, so scripts see one code for "did not run to completion").
const FAILURE_EXIT_CODE: u8 = 2;

/// Runs the parsed command; an error is printed as `error: …` on stderr.
pub fn run(cli: Cli) -> ExitCode {
    if !matches!(cli.command, Command::Serve(_)) {
        restore_default_sigpipe();
    }
    let result = match cli.command {
        Command::Solve(args) => solve::run(args),
        Command::Serve(args) => serve::run(args),
        Command::Ba(args) => ba::run(args),
        Command::DirectBa(args) => direct_ba::run(args),
        Command::FusionEval(args) => fusion_eval::run(args),
        Command::BenchCholesky(args) => bench_cholesky::run(args),
        // Exit codes of its own: Docker's HEALTHCHECK reads 1 as unhealthy and reserves 2.
        Command::Health(args) => return health::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {error}");
            ExitCode::from(FAILURE_EXIT_CODE)
        }
    }
}

/// Batch commands piped into `head` should stop quietly when the reader goes away, as Unix tools
/// do, not panic on the failed write. The server keeps Rust's default (SIGPIPE ignored) so a
/// client hanging up never kills it.
fn restore_default_sigpipe() {
    // SAFETY: called from `main` before any other thread exists; SIG_DFL is a valid disposition.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}
