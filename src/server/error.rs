//! Why `factord serve` could not start or stopped: each a one-line reason for the operator.

use std::path::PathBuf;

use crate::transport::zenoh;

#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error("authentication: {0}")]
    Auth(String),
    #[error("config file {file}: {message}")]
    Config { file: PathBuf, message: String },
    #[error("state directory {dir}: {message}")]
    StateDir { dir: PathBuf, message: String },
    #[error("cannot listen on {addr}: {source}")]
    Listen {
        addr: String,
        source: std::io::Error,
    },
    #[error(transparent)]
    Zenoh(#[from] zenoh::ZenohError),
    #[error("HTTP server: {0}")]
    Http(std::io::Error),
    #[error("fleet: {0}")]
    Fleet(String),
}
