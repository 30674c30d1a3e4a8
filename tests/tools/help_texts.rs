//! Every subcommand's `--help` as a new user reads it (issue 56): every option says what it is
//! (a line with only a default or nothing at all fails), no default is printed twice, and no
//! line leans on "the course" without naming it. fusion-eval's options are all in its guide.

use crate::common;

use common::cli::{factord, Run};

/// The subcommands `factord --help` lists (`help` aside).
fn subcommands() -> Vec<String> {
    let help = factord().arg("--help").succeeds();
    let help = String::from_utf8(help.stdout).unwrap();
    help.lines()
        .skip_while(|l| !l.starts_with("Commands:"))
        .skip(1)
        .take_while(|l| l.starts_with("  "))
        .filter_map(|l| l.split_whitespace().next())
        .filter(|name| *name != "help")
        .map(str::to_string)
        .collect()
}

/// The option entries of a help text: (flags, description with every line after the flags up to
/// the next option), as clap prints them in either layout (two columns, or the description on the
/// following lines).
fn options(help: &str) -> Vec<(String, String)> {
    let mut entries: Vec<(String, String)> = Vec::new();
    let mut in_options = false;
    for line in help.lines() {
        if line.starts_with("Options:") {
            in_options = true;
            continue;
        }
        if !in_options {
            continue;
        }
        let trimmed = line.trim_start();
        let indent = line.len() - trimmed.len();
        if trimmed.starts_with('-') && (2..=6).contains(&indent) {
            // `-h, --help`, `--edges <EDGES>`, `--zenoh-listen <ZENOH_LISTEN>...`: the flags
            // end at the first run of two spaces (or the line's end).
            let (flags, rest) = trimmed.split_once("  ").unwrap_or((trimmed, ""));
            entries.push((flags.to_string(), rest.trim().to_string()));
        } else if let Some(last) = entries.last_mut() {
            last.1.push(' ');
            last.1.push_str(trimmed);
        }
    }
    entries
}

/// `text` without clap's bracketed annotations (`[default: …]`, `[env: …]`, `[possible values:
/// …]`, `[aliases: …]`).
fn without_annotations(text: &str) -> String {
    let mut out = text.to_string();
    for tag in ["[default: ", "[env: ", "[possible values: ", "[aliases: "] {
        while let Some(start) = out.find(tag) {
            let end = out[start..].find(']').map_or(out.len(), |e| start + e + 1);
            out.replace_range(start..end, "");
        }
    }
    out.trim().to_string()
}

#[test]
fn every_option_of_every_subcommand_says_what_it_is() {
    let commands = subcommands();
    assert!(commands.len() >= 7, "{commands:?}");
    let mut problems = Vec::new();
    for command in &commands {
        let output = factord().args([command.as_str(), "--help"]).succeeds();
        let help = String::from_utf8(output.stdout).unwrap();
        let entries = options(&help);
        assert!(!entries.is_empty(), "{command}: no options parsed:\n{help}");
        for (flags, description) in &entries {
            if without_annotations(description).is_empty() {
                problems.push(format!("{command} {flags}: no description"));
            }
            if description.matches("[default: ").count() > 1 {
                problems.push(format!(
                    "{command} {flags}: a default printed twice: {description}"
                ));
            }
        }
        for line in help.lines() {
            if line.contains("the course") {
                problems.push(format!(
                    "{command}: says \"the course\" without naming it: {}",
                    line.trim()
                ));
            }
        }
    }
    let top = String::from_utf8(factord().arg("--help").succeeds().stdout).unwrap();
    for line in top.lines().filter(|l| l.contains("the course")) {
        problems.push(format!(
            "factord: says \"the course\" without naming it: {}",
            line.trim()
        ));
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

/// The parser above finds what it must: a description-less option and a doubled default.
#[test]
fn the_help_parser_sees_missing_descriptions_and_doubled_defaults() {
    let help = "Usage: x\n\nOptions:\n      --edges <EDGES>          \n      --repeat <REPEAT>        [default: 50]\n      --log <LOG>\n          Log filter [default: info]\n          \n          [env: FACTORD_LOG=]\n          [default: info]\n  -h, --help                   Print help\n";
    let entries = options(help);
    let flags: Vec<&str> = entries.iter().map(|e| e.0.as_str()).collect();
    assert_eq!(
        flags,
        [
            "--edges <EDGES>",
            "--repeat <REPEAT>",
            "--log <LOG>",
            "-h, --help"
        ]
    );
    assert_eq!(without_annotations(&entries[0].1), "");
    assert_eq!(without_annotations(&entries[1].1), "");
    assert_eq!(entries[2].1.matches("[default: ").count(), 2);
    assert_eq!(without_annotations(&entries[3].1), "Print help");
}

/// fusion-eval's guide block lists every option its `--help` has.
#[test]
fn the_fusion_eval_guide_lists_every_option() {
    let help =
        String::from_utf8(factord().args(["fusion-eval", "--help"]).succeeds().stdout).unwrap();
    let guide = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/docs/guide/sliding-windows.md"
    ))
    .unwrap();
    let block = guide
        .split("factord fusion-eval [")
        .nth(1)
        .and_then(|b| b.split("```").next())
        .expect("the usage block");
    for (flags, _) in options(&help) {
        let long = flags
            .split_whitespace()
            .find(|f| f.starts_with("--"))
            .unwrap()
            .trim_end_matches(',');
        if long == "--help" {
            continue;
        }
        assert!(
            block.contains(long),
            "{long} is missing from the guide's block:\n{block}"
        );
    }
}
