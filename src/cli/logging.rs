//! The server's log output on stderr: which events pass (`--log`, RUST_LOG syntax), and how they
//! are written (`--log-format`; colours only when a person is watching a terminal).

use std::io::IsTerminal;

use tracing_subscriber::filter::LevelFilter;
use tracing_subscriber::EnvFilter;

use super::CliError;

/// A validated `--log` value: a level (`info`) or comma-separated directives as in RUST_LOG
/// (`factord=debug,zenoh=warn`). Kept as text because `EnvFilter` is not `Clone`, which clap needs.
#[derive(Clone, Debug)]
pub struct LogFilter(String);

/// `--log` syntax. A single bare word must be a level: `EnvFilter` would read a misspelt level
/// (`--log verbose`) as a target name and quietly log nothing, where a level flag should refuse
/// it; a target on its own is written `target=trace`.
pub fn parse_log_filter(s: &str) -> Result<LogFilter, String> {
    let is_directive_list = s.contains(['=', ',', '[']);
    if !is_directive_list && s.parse::<LevelFilter>().is_err() {
        return Err(format!(
            "`{s}`: expected a level (error, warn, info, debug, trace, off) or directives such as factord=debug,zenoh=warn"
        ));
    }
    EnvFilter::try_new(s)
        .map(|_| LogFilter(s.to_string()))
        .map_err(|e| format!("`{s}`: {e}"))
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum LogFormat {
    /// One human-readable line per event.
    Text,
    /// One JSON object per line, with `timestamp`, `level`, `target`, `message`, the event's
    /// fields and its spans, for log collectors.
    Json,
}

/// Installs the process-wide subscriber writing to stderr.
pub fn init(filter: &LogFilter, format: LogFormat) -> Result<(), CliError> {
    // Validated by `parse_log_filter`, so this parse cannot fail on a value from clap.
    let filter = EnvFilter::try_new(&filter.0)
        .map_err(|e| CliError::Reported(format!("--log `{}`: {e}", filter.0)))?;
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    match format {
        // Escape codes in a redirected file or a journald capture are noise, not colour.
        LogFormat::Text => builder
            .with_ansi(std::io::stderr().is_terminal())
            .try_init(),
        LogFormat::Json => builder.json().flatten_event(true).try_init(),
    }
    .map_err(CliError::Logging)
}
