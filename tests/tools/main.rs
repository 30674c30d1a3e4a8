//! The command-line tools, logging, the Docker files, the Python client and the test environments.
//!
//! One test binary per area (each file below was a binary of its own): a change to the library
//! relinks a handful of binaries instead of sixty. Run one file's tests with
//! `cargo test --release --test tools <file>::`.

#[path = "../common/mod.rs"]
mod common;

mod cli;
mod cli_output;
mod cli_robots;
mod doc_links;
mod docker;
mod docker_run;
mod fresh_environments;
mod help_texts;
mod logging;
mod python;
mod python_native;
mod secrets_ignored;
