//! `factord`: command-line entry point. The subcommands live in `cli/`, one file each.

use std::process::ExitCode;

use clap::Parser;

mod cli;
#[path = "../eval/mod.rs"]
mod eval;

fn main() -> ExitCode {
    cli::run(cli::Cli::parse())
}
