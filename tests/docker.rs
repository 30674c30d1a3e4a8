//! No Docker engine runs here, so the container files are checked by reading: every path they
//! copy exists, every `factord` flag they pass is one the binary accepts, and the ports they
//! publish are the ones the defaults and flags use.

use std::path::PathBuf;
use std::process::Command;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn read(path: &str) -> String {
    std::fs::read_to_string(repo().join(path)).unwrap_or_else(|e| panic!("{path}: {e}"))
}

fn serve_help() -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_factord"))
        .args(["serve", "--help"])
        .output()
        .expect("factord runs");
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// The JSON array of an exec-form instruction (`ENTRYPOINT [...]`).
fn exec_form(dockerfile: &str, instruction: &str) -> Vec<String> {
    let line = dockerfile
        .lines()
        .find(|l| l.starts_with(instruction))
        .unwrap_or_else(|| panic!("no {instruction}"));
    serde_json::from_str(line[instruction.len()..].trim()).expect("exec form is a JSON array")
}

fn assert_flags_exist(args: &[String], help: &str) {
    for flag in args.iter().filter(|a| a.starts_with("--")) {
        assert!(help.contains(flag.as_str()), "factord serve has no {flag}");
    }
}

#[test]
fn dockerfile_copies_existing_paths_and_runs_real_flags() {
    let dockerfile = read("docker/Dockerfile");
    let help = serve_help();
    for line in dockerfile
        .lines()
        .filter(|l| l.starts_with("COPY ") && !l.contains("--from"))
    {
        let parts: Vec<&str> = line.split_whitespace().collect();
        for source in &parts[1..parts.len() - 1] {
            assert!(repo().join(source).exists(), "COPY {source}: missing");
        }
    }
    let entry = exec_form(&dockerfile, "ENTRYPOINT");
    assert_eq!(entry[..2], ["factord", "serve"]);
    assert_flags_exist(&entry, &help);
    let value = |flag: &str| entry[entry.iter().position(|a| a == flag).unwrap() + 1].clone();
    assert!(value("--listen").ends_with(":8080"));
    assert!(value("--zenoh-listen").ends_with(":7447"));
    let expose = dockerfile
        .lines()
        .find(|l| l.starts_with("EXPOSE"))
        .expect("EXPOSE");
    assert!(
        expose.contains("8080") && expose.contains("7447"),
        "{expose}"
    );
    let state = value("--state-dir");
    assert!(
        dockerfile.contains(&format!("VOLUME {state}")),
        "state dir is a volume"
    );
    // The binary the build stage produces is the one the manifest defines.
    assert!(read("Cargo.toml").contains("name = \"factord\""));
}

#[test]
fn compose_wires_factord_to_the_router() {
    let compose = read("docker/compose.yaml");
    let help = serve_help();
    // The entrypoint list of the factord service.
    let args: Vec<String> = compose
        .lines()
        .skip_while(|l| !l.trim_start().starts_with("entrypoint:"))
        .skip(1)
        .take_while(|l| l.trim_start().starts_with("- "))
        .map(|l| l.trim_start()[2..].trim().to_string())
        .collect();
    assert_eq!(args[..2], ["factord", "serve"], "{args:?}");
    assert_flags_exist(&args, &help);
    let connect = &args[args.iter().position(|a| a == "--zenoh-connect").unwrap() + 1];
    assert_eq!(connect, "tcp/zenohd:7447");
    assert!(compose.contains("zenohd:") && compose.contains("\"7447:7447\""));
    assert!(compose.contains("\"8080:8080\""));
    assert!(compose.contains("dockerfile: docker/Dockerfile"));
    assert!(repo().join("docker/Dockerfile").is_file());
    // Environment variables it sets are ones factord reads.
    for var in compose
        .lines()
        .filter_map(|l| l.trim().strip_prefix("FACTORD_"))
    {
        let name = format!("FACTORD_{}", var.split(':').next().unwrap());
        assert!(help.contains(&name), "factord reads no {name}");
    }
}
