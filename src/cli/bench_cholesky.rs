//! `factord bench-cholesky`: time the numeric sparse Cholesky of a graph's normal equations at its
//! optimum, and write the matrix in Matrix Market form for comparison with other libraries.

use std::path::PathBuf;

use factord::solver::cholesky_bench;

use super::stdio::{one_stdin, InputArg};
use super::CliError;

#[derive(clap::Args)]
pub struct BenchCholeskyArgs {
    /// Graph file; `-` reads standard input. A relative path not found here is looked up under
    /// $FACTORD_DATA.
    graph: InputArg,
    #[arg(long)]
    edges: Option<InputArg>,
    #[arg(long, default_value_t = 50)]
    repeat: usize,
    /// Matrix Market output of H (lower triangle, symmetric).
    #[arg(long)]
    write_mtx: Option<PathBuf>,
}

pub fn run(args: BenchCholeskyArgs) -> Result<(), CliError> {
    one_stdin(&[
        ("graph", Some(&args.graph)),
        ("--edges", args.edges.as_ref()),
    ])?;
    let text = args.graph.read_to_string("graph")?;
    let edges = match &args.edges {
        Some(input) => Some((input.name(), input.read_to_string("--edges")?)),
        None => None,
    };
    let mut graph = factord::io::parse_pair(
        (&args.graph.name(), &text),
        edges
            .as_ref()
            .map(|(name, text)| (name.as_path(), text.as_str())),
    )?;
    let report = cholesky_bench::run(&mut graph.problem, args.repeat, args.write_mtx.as_deref())
        .map_err(|e| CliError::Reported(e.to_string()))?;
    println!("{report}");
    Ok(())
}
