//! `factord serve` logging on a redirected stderr: plain text without colour codes, one JSON
//! object per line with `--log-format json`, and RUST_LOG-style directives in `--log`.

use crate::common;

use std::time::Duration;

use common::server::TestServer;

/// Starts a server with `extra` flags, stops it with SIGTERM and returns its whole log (start-up
/// and shutdown lines both written by then).
fn log_of_a_run(extra: &[&str]) -> String {
    let mut flags = vec!["--no-zenoh", "--no-journal"];
    flags.extend_from_slice(extra);
    let server = TestServer::start(&flags);
    let (status, log) = server.terminate(Duration::from_secs(20));
    assert!(status.is_some_and(|s| s.success()), "{status:?}\n{log}");
    log
}

#[test]
fn text_logs_written_to_a_file_carry_no_colour_codes() {
    let log = log_of_a_run(&[]);
    assert!(log.contains("serving HTTP on"), "{log}");
    assert!(
        !log.contains("\x1b["),
        "ANSI escape codes in a redirected log:\n{log:?}"
    );
}

#[test]
fn json_logs_are_one_object_per_line_with_level_and_message() {
    let log = log_of_a_run(&["--log-format", "json"]);
    let lines: Vec<&str> = log.lines().filter(|l| !l.trim().is_empty()).collect();
    assert!(!lines.is_empty(), "no log lines");
    for line in &lines {
        let event: serde_json::Value =
            serde_json::from_str(line).unwrap_or_else(|e| panic!("{e}: not JSON: {line}"));
        assert!(event.is_object(), "{line}");
        assert!(event["level"].is_string(), "no level: {line}");
        assert!(event["message"].is_string(), "no message: {line}");
    }
    assert!(lines.iter().any(|l| l.contains("serving HTTP on")), "{log}");
}

#[test]
fn log_format_comes_from_the_environment_too() {
    let server = TestServer::start_with_env(
        &["--no-zenoh", "--no-journal"],
        &[("FACTORD_LOG_FORMAT", "json")],
    );
    let (_, log) = server.terminate(Duration::from_secs(20));
    let first = log.lines().next().expect("a log line");
    assert!(
        serde_json::from_str::<serde_json::Value>(first).is_ok(),
        "{log}"
    );
}

#[test]
fn log_directives_filter_by_target() {
    // factord's start-up and shutdown lines are at info, so `factord=warn` leaves them out.
    let log = log_of_a_run(&["--log", "factord=warn"]);
    assert!(!log.contains("serving HTTP on"), "{log}");
    let log = log_of_a_run(&["--log", "factord=info,zenoh=warn"]);
    assert!(log.contains("serving HTTP on"), "{log}");
}

#[test]
fn a_misspelt_level_is_refused() {
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_factord"))
        .args(["serve", "--log", "verbose"])
        .output()
        .expect("factord runs");
    assert_eq!(output.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("expected a level"), "{stderr}");
}
