//! `factord bench-cholesky`: time the numeric sparse Cholesky of a graph's normal equations at its
//! optimum, and write the matrix in Matrix Market form for comparison with other libraries.

use crate::eval::cholesky_bench;

use super::stdio::{one_stdin, one_stdout, InputArg, OutputArg};
use super::CliError;

#[derive(clap::Args)]
pub struct BenchCholeskyArgs {
    /// Graph file; `-` reads standard input. A relative path not found here is looked up under
    /// $FACTORD_DATA.
    graph: InputArg,
    /// Edges file, when vertices and edges are in two files (TORO `-v.dat` / `-e.dat` pairs)
    #[arg(long)]
    edges: Option<InputArg>,
    /// Factorise (and solve) this many times at the optimum; the table gives the median times
    #[arg(long, default_value_t = 50)]
    repeat: usize,
    /// Matrix Market output of H (lower triangle, symmetric); `-` for standard output.
    #[arg(long)]
    write_mtx: Option<OutputArg>,
    /// Print the timings as one line of JSON instead of a table.
    #[arg(long)]
    json: bool,
}

pub fn run(args: BenchCholeskyArgs) -> Result<(), CliError> {
    one_stdin(&[
        ("graph", Some(&args.graph)),
        ("--edges", args.edges.as_ref()),
    ])?;
    let json_target = OutputArg::Stdout;
    one_stdout(&[
        ("--json", args.json.then_some(&json_target)),
        ("--write-mtx", args.write_mtx.as_ref()),
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
    let bench = cholesky_bench::run(&mut graph.problem, args.repeat, args.write_mtx.is_some())
        .map_err(|e| CliError::Reported(e.to_string()))?;
    if let (Some(target), Some(matrix)) = (&args.write_mtx, &bench.matrix_market) {
        target.write("--write-mtx", matrix.as_bytes())?;
    }
    if args.json {
        println!("{}", bench.report);
    } else {
        let table = table(&bench.report)?;
        match &args.write_mtx {
            Some(target) if target.is_stdout() => eprint!("{table}"),
            _ => print!("{table}"),
        }
    }
    Ok(())
}

/// The JSON report as a table: one row per factorisation choice.
fn table(report: &str) -> Result<String, CliError> {
    let json: serde_json::Value = serde_json::from_str(report)?;
    let mut out = format!(
        "H: n {}, nnz (lower) {}\n{:<12}{:>12}{:>16}{:>16}{:>16}{:>14}\n",
        json["n"],
        json["nnz_lower"],
        "threshold",
        "kind",
        "numeric (s)",
        "solve (s)",
        "analyse (s)",
        "L nnz"
    );
    for choice in ["auto", "supernodal", "simplicial"] {
        let row = &json[choice];
        out += &format!(
            "{choice:<12}{:>12}{:>16.6e}{:>16.6e}{:>16.6e}{:>14}\n",
            row["kind"].as_str().unwrap_or("?"),
            row["numeric_seconds"].as_f64().unwrap_or(f64::NAN),
            row["solve_seconds"].as_f64().unwrap_or(f64::NAN),
            row["analyze_seconds"].as_f64().unwrap_or(f64::NAN),
            // Value's Display ignores widths: format the number itself.
            row["factor_nnz"].to_string()
        );
    }
    Ok(out)
}
