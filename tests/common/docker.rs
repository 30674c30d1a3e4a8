//! Reading the container files (docker/Dockerfile, docker/compose.yaml) for the tests that
//! check them (`tests/tools/docker.rs`) and run their command lines (`tests/tools/docker_run.rs`).

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::Command;

use serde_yaml::Value as Yaml;

pub fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

pub fn read(path: &str) -> String {
    std::fs::read_to_string(repo().join(path)).unwrap_or_else(|e| panic!("{path}: {e}"))
}

pub fn factord() -> Command {
    Command::new(env!("CARGO_BIN_EXE_factord"))
}

pub fn serve_help() -> String {
    let out = factord().args(["serve", "--help"]).output().unwrap();
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// The package's version in Cargo.toml, and a locked crate's version in Cargo.lock.
pub fn crate_version() -> String {
    env!("CARGO_PKG_VERSION").to_string()
}

pub fn locked_version(name: &str) -> String {
    let lock = read("Cargo.lock");
    let at = lock
        .find(&format!("name = \"{name}\"\nversion = \""))
        .unwrap_or_else(|| panic!("{name} is not in Cargo.lock"));
    let rest = &lock[at..];
    let start = rest.find("version = \"").unwrap() + "version = \"".len();
    rest[start..start + rest[start..].find('"').unwrap()].to_string()
}

// ---- the Dockerfile --------------------------------------------------------------------------

/// The Dockerfile's instructions (keyword, arguments), continuation lines joined, comments
/// dropped.
pub fn instructions(dockerfile: &str) -> Vec<(String, String)> {
    let mut out = Vec::new();
    let mut current = String::new();
    for line in dockerfile.lines() {
        let trimmed = line.trim();
        if trimmed.starts_with('#') || (trimmed.is_empty() && current.is_empty()) {
            continue;
        }
        match trimmed.strip_suffix('\\') {
            Some(part) => {
                current.push_str(part);
                current.push(' ');
            }
            None => {
                current.push_str(trimmed);
                let (keyword, args) = current.split_once(' ').unwrap_or((&current, ""));
                out.push((keyword.to_ascii_uppercase(), args.trim().to_string()));
                current.clear();
            }
        }
    }
    out
}

pub fn dockerfile() -> Vec<(String, String)> {
    instructions(&read("docker/Dockerfile"))
}

pub fn json_array(text: &str) -> Vec<String> {
    serde_json::from_str(text).unwrap_or_else(|e| panic!("not an exec-form array: {text}: {e}"))
}

/// The image's ENTRYPOINT and the HEALTHCHECK's command.
pub fn entrypoint() -> Vec<String> {
    let (_, args) = dockerfile()
        .into_iter()
        .find(|(k, _)| k == "ENTRYPOINT")
        .expect("ENTRYPOINT");
    json_array(&args)
}

pub fn healthcheck() -> Vec<String> {
    let (_, args) = dockerfile()
        .into_iter()
        .find(|(k, _)| k == "HEALTHCHECK")
        .expect("HEALTHCHECK");
    let cmd = args.find("CMD ").expect("HEALTHCHECK ... CMD [...]");
    json_array(args[cmd + 4..].trim())
}

/// `name:tag` is pinned: a tag that names an exact release (three numbers, or a date stamp),
/// never `latest` or a moving major/minor tag.
pub fn assert_pinned(image: &str) {
    let (_, tag) = image
        .rsplit_once(':')
        .unwrap_or_else(|| panic!("{image}: no tag"));
    let tag = tag.split('@').next().unwrap();
    let exact_version = tag.split('-').any(|part| {
        part.split('.').count() == 3 && part.split('.').all(|n| n.parse::<u32>().is_ok())
    });
    let date_stamp = tag
        .split('-')
        .any(|part| part.len() == 8 && part.bytes().all(|b| b.is_ascii_digit()));
    assert!(
        !tag.contains("latest") && (exact_version || date_stamp),
        "{image}: not pinned to an exact release"
    );
}

// ---- docker/compose.yaml ---------------------------------------------------------------------

pub fn compose() -> Yaml {
    let mut doc: Yaml = serde_yaml::from_str(&read("docker/compose.yaml")).expect("valid YAML");
    doc.apply_merge().expect("merge keys");
    doc
}

pub fn strings(value: &Yaml) -> Vec<String> {
    match value {
        Yaml::Sequence(items) => items
            .iter()
            .map(|v| v.as_str().expect("a string").to_string())
            .collect(),
        Yaml::String(s) => s.split_whitespace().map(str::to_string).collect(),
        Yaml::Null => Vec::new(),
        other => panic!("not a list of strings: {other:?}"),
    }
}

pub fn factord_services(doc: &Yaml) -> Vec<(String, Yaml)> {
    let services = doc["services"].as_mapping().expect("services");
    services
        .iter()
        .map(|(k, v)| (k.as_str().unwrap().to_string(), v.clone()))
        .filter(|(k, _)| k.starts_with("factord"))
        .collect()
}

/// The environment a service sets (map or `KEY=value` list form).
pub fn environment(service: &Yaml) -> BTreeMap<String, String> {
    match &service["environment"] {
        Yaml::Mapping(m) => m
            .iter()
            .map(|(k, v)| {
                let value = match v {
                    Yaml::String(s) => s.clone(),
                    other => serde_yaml::to_string(other).unwrap().trim().to_string(),
                };
                (k.as_str().unwrap().to_string(), value)
            })
            .collect(),
        Yaml::Sequence(_) => strings(&service["environment"])
            .into_iter()
            .map(|kv| {
                let (k, v) = kv.split_once('=').expect("KEY=value");
                (k.to_string(), v.to_string())
            })
            .collect(),
        _ => BTreeMap::new(),
    }
}

/// What the container runs: the service's entrypoint (else the image's) and its command.
pub fn service_argv(service: &Yaml) -> Vec<String> {
    let mut argv = match &service["entrypoint"] {
        Yaml::Null => entrypoint(),
        e => strings(e),
    };
    argv.extend(strings(&service["command"]));
    argv
}

pub fn flag_value(argv: &[String], flag: &str) -> Option<String> {
    argv.iter()
        .position(|a| a == flag)
        .map(|i| argv[i + 1].clone())
}

/// Where a service's secret `name` is mounted (`/run/secrets/<target or name>`).
pub fn secret_path(service: &Yaml, name: &str) -> Option<String> {
    service["secrets"]
        .as_sequence()?
        .iter()
        .find_map(|s| match s {
            Yaml::String(n) if n == name => Some(format!("/run/secrets/{name}")),
            Yaml::Mapping(_) if s["source"].as_str() == Some(name) => {
                let target = s["target"].as_str().unwrap_or(name);
                Some(match target.starts_with('/') {
                    true => target.to_string(),
                    false => format!("/run/secrets/{target}"),
                })
            }
            _ => None,
        })
}
