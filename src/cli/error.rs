//! The error every subcommand returns; `main` prints it as `error: …` and exits with 2.

use std::path::PathBuf;

use factord::fusion::window::FusionError;
use factord::io::IoError;
use factord::server::ServeError;
use factord::solver::SolverError;

#[derive(Debug, thiserror::Error)]
pub enum CliError {
    #[error(transparent)]
    Io(#[from] IoError),
    #[error(transparent)]
    Solver(#[from] SolverError),
    #[error(transparent)]
    Fusion(#[from] FusionError),
    #[error(transparent)]
    Serve(#[from] ServeError),
    /// Reading an input argument (a file or `-`); `hint` says where else it was looked for.
    #[error("{argument} {}: cannot read: {source}{hint}", path.display())]
    Read {
        argument: String,
        path: PathBuf,
        source: std::io::Error,
        hint: String,
    },
    /// Writing an output argument (a file or `-`).
    #[error("{argument} {}: cannot write: {source}", path.display())]
    Write {
        argument: String,
        path: PathBuf,
        source: std::io::Error,
    },
    /// An argument clap accepted that does not fit with the others or the data.
    #[error("{argument}: {reason}")]
    Argument { argument: String, reason: String },
    /// A JSON file the command reads that does not hold what it should.
    #[error("{}: {source}", path.display())]
    FileContents {
        path: PathBuf,
        source: serde_json::Error,
    },
    /// Turning a result into JSON.
    #[error(transparent)]
    Json(#[from] serde_json::Error),
    /// The tokio runtime could not be built (threads or the I/O driver).
    #[error("{0}")]
    Runtime(std::io::Error),
    /// A second global log subscriber (only a bug can cause it).
    #[error("cannot install the log subscriber: {0}")]
    Logging(Box<dyn std::error::Error + Send + Sync>),
    /// Library functions that still report their errors as text (fusion input generation, the
    /// zenoh stream, the Cholesky benchmark).
    #[error("{0}")]
    Reported(String),
}
