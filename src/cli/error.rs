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
    /// Reading or writing a file the command handles itself (not through `factord::io`).
    #[error("{}: {source}", path.display())]
    File {
        path: PathBuf,
        source: std::io::Error,
    },
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

impl CliError {
    pub fn file(path: impl Into<PathBuf>) -> impl FnOnce(std::io::Error) -> Self {
        let path = path.into();
        move |source| Self::File { path, source }
    }
}
