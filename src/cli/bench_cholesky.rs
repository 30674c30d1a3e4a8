//! `factord bench-cholesky`: time the numeric sparse Cholesky of a graph's normal equations at its
//! optimum, and write the matrix in Matrix Market form for comparison with other libraries.

use std::path::PathBuf;

use factord::solver::cholesky_bench;

use super::CliError;

#[derive(clap::Args)]
pub struct BenchCholeskyArgs {
    graph: PathBuf,
    #[arg(long)]
    edges: Option<PathBuf>,
    #[arg(long, default_value_t = 50)]
    repeat: usize,
    /// Matrix Market output of H (lower triangle, symmetric).
    #[arg(long)]
    write_mtx: Option<PathBuf>,
}

pub fn run(args: BenchCholeskyArgs) -> Result<(), CliError> {
    let mut graph = factord::io::load(&args.graph, args.edges.as_deref())
        .map_err(|e| CliError::Reported(e.to_string()))?;
    let report = cholesky_bench::run(&mut graph.problem, args.repeat, args.write_mtx.as_deref())
        .map_err(|e| CliError::Reported(e.to_string()))?;
    println!("{report}");
    Ok(())
}
