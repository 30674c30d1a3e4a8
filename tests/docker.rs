//! The container files and `factord health`, checked without a container engine (none runs
//! here): the Dockerfile and docker/compose.yaml are read and held to the rules they promise
//! (pinned tags, a dependency layer, a non-root user, health checks, tokens, one shared volume),
//! and the command lines they would run are run: each compose service's `factord serve` as a
//! real process, with paths moved to a temporary directory and ports to free ones, a zenoh router
//! from our zenoh crate standing in for zenohd, and the services' health checks against them.

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use common::server::{free_port, TestServer};
use serde_yaml::Value as Yaml;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn read(path: &str) -> String {
    std::fs::read_to_string(repo().join(path)).unwrap_or_else(|e| panic!("{path}: {e}"))
}

fn factord() -> Command {
    Command::new(env!("CARGO_BIN_EXE_factord"))
}

fn serve_help() -> String {
    let out = factord().args(["serve", "--help"]).output().unwrap();
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// The package's version in Cargo.toml, and a locked crate's version in Cargo.lock.
fn crate_version() -> String {
    env!("CARGO_PKG_VERSION").to_string()
}

fn locked_version(name: &str) -> String {
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
fn instructions(dockerfile: &str) -> Vec<(String, String)> {
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

fn dockerfile() -> Vec<(String, String)> {
    instructions(&read("docker/Dockerfile"))
}

fn json_array(text: &str) -> Vec<String> {
    serde_json::from_str(text).unwrap_or_else(|e| panic!("not an exec-form array: {text}: {e}"))
}

/// The image's ENTRYPOINT and the HEALTHCHECK's command.
fn entrypoint() -> Vec<String> {
    let (_, args) = dockerfile()
        .into_iter()
        .find(|(k, _)| k == "ENTRYPOINT")
        .expect("ENTRYPOINT");
    json_array(&args)
}

fn healthcheck() -> Vec<String> {
    let (_, args) = dockerfile()
        .into_iter()
        .find(|(k, _)| k == "HEALTHCHECK")
        .expect("HEALTHCHECK");
    let cmd = args.find("CMD ").expect("HEALTHCHECK ... CMD [...]");
    json_array(args[cmd + 4..].trim())
}

/// `name:tag` is pinned: a tag that names an exact release (three numbers, or a date stamp),
/// never `latest` or a moving major/minor tag.
fn assert_pinned(image: &str) {
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

#[test]
fn dockerfile_pins_its_bases_builds_dependencies_first_and_runs_unprivileged() {
    let steps = dockerfile();
    let froms: Vec<&String> = steps
        .iter()
        .filter(|(k, _)| k == "FROM")
        .map(|(_, a)| a)
        .collect();
    assert_eq!(froms.len(), 2, "a build and a runtime stage");
    for from in &froms {
        assert_pinned(from.split_whitespace().next().unwrap());
    }
    // Build and runtime on the same Debian release (the binary's glibc).
    assert!(
        froms[0].contains("bookworm") && froms[1].contains("bookworm"),
        "{froms:?}"
    );
    // Every path copied from the context exists and is not kept out by .dockerignore.
    let ignored = read(".dockerignore");
    for (_, args) in steps
        .iter()
        .filter(|(k, a)| k == "COPY" && !a.starts_with("--from"))
    {
        let parts: Vec<&str> = args.split_whitespace().collect();
        for source in &parts[..parts.len() - 1] {
            assert!(repo().join(source).exists(), "COPY {source}: missing");
            let top = source.split('/').next().unwrap();
            assert!(
                !ignored
                    .lines()
                    .any(|l| l.trim_end_matches('/') == top || l == *source),
                "COPY {source}: excluded by .dockerignore"
            );
        }
    }
    // The real tokens file never enters the build context.
    assert!(
        ignored.lines().any(|l| l == "docker/tokens"),
        ".dockerignore: docker/tokens"
    );

    // The dependency layer: manifest and lockfile alone, built, and only then the sources.
    let position = |pred: &dyn Fn(&(String, String)) -> bool| {
        steps.iter().position(pred).expect("instruction present")
    };
    let manifest = position(&|(k, a)| k == "COPY" && a.starts_with("Cargo.toml Cargo.lock "));
    let deps_build = position(&|(k, a)| {
        k == "RUN" && a.contains("stub-sources.sh") && a.contains("cargo build --release --locked")
    });
    let sources = position(&|(k, a)| k == "COPY" && a.starts_with("src "));
    let real_build = steps.len()
        - 1
        - steps
            .iter()
            .rev()
            .position(|(k, a)| k == "RUN" && a.contains("cargo build --release --locked"))
            .unwrap();
    assert!(manifest < deps_build && deps_build < sources && sources < real_build);
    // The stub's artefacts go before the real build, and the real binary proves itself.
    assert!(steps[deps_build]
        .1
        .contains("target/release/.fingerprint/factord-*"));
    assert!(steps[real_build].1.contains("factord --version"));

    // The runtime stage runs as an unprivileged user, set before the entrypoint.
    let runtime = steps.iter().rposition(|(k, _)| k == "FROM").unwrap();
    let user = steps[runtime..]
        .iter()
        .find(|(k, _)| k == "USER")
        .map(|(_, a)| a.clone())
        .expect("USER in the runtime stage");
    assert!(user != "root" && !user.starts_with("0"), "USER {user}");

    // The entrypoint's ports and state directory are the ones the image declares.
    let entry = entrypoint();
    assert_eq!(entry[..2], ["factord", "serve"]);
    let value = |flag: &str| entry[entry.iter().position(|a| a == flag).unwrap() + 1].clone();
    let expose = &steps.iter().find(|(k, _)| k == "EXPOSE").expect("EXPOSE").1;
    for port in [value("--listen"), value("--zenoh-listen")] {
        let port = port.rsplit(':').next().unwrap().to_string();
        assert!(
            expose.split_whitespace().any(|p| p == port),
            "EXPOSE {expose} lacks {port}"
        );
    }
    let state = value("--state-dir");
    assert!(steps.iter().any(|(k, a)| k == "VOLUME" && *a == state));
    assert_eq!(healthcheck()[..2], ["factord", "health"]);
}

/// The stub script gives every target the manifest names a file, so the dependency build never
/// fails on a missing one, and writes nothing cargo would take for one of our real sources.
#[test]
fn dependency_stubs_cover_every_cargo_target() {
    let dir = common::temp_dir("stubs");
    for file in ["Cargo.toml", "Cargo.lock"] {
        std::fs::copy(repo().join(file), dir.join(file)).unwrap();
    }
    let status = Command::new("sh")
        .arg(repo().join("docker/stub-sources.sh"))
        .current_dir(&dir)
        .status()
        .unwrap();
    assert!(status.success());
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .args([
            "metadata",
            "--no-deps",
            "--offline",
            "--format-version",
            "1",
        ])
        .current_dir(&dir)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let meta: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let targets = meta["packages"][0]["targets"].as_array().unwrap();
    let mut kinds = Vec::new();
    for target in targets {
        let path = target["src_path"].as_str().unwrap();
        assert!(Path::new(path).is_file(), "no stub for {path}");
        kinds.push(target["kind"][0].as_str().unwrap().to_string());
    }
    assert!(
        kinds.contains(&"lib".into()) && kinds.contains(&"bin".into()),
        "{kinds:?}"
    );
    assert!(
        kinds.iter().filter(|k| *k == "bench").count() >= 1,
        "{kinds:?}"
    );
    let main = std::fs::read_to_string(dir.join("src/main.rs")).unwrap();
    assert!(
        main.contains("exit(99)"),
        "a stub binary kept by mistake fails --version"
    );
}

// ---- docker/compose.yaml ---------------------------------------------------------------------

fn compose() -> Yaml {
    let mut doc: Yaml = serde_yaml::from_str(&read("docker/compose.yaml")).expect("valid YAML");
    doc.apply_merge().expect("merge keys");
    doc
}

fn strings(value: &Yaml) -> Vec<String> {
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

fn factord_services(doc: &Yaml) -> Vec<(String, Yaml)> {
    let services = doc["services"].as_mapping().expect("services");
    services
        .iter()
        .map(|(k, v)| (k.as_str().unwrap().to_string(), v.clone()))
        .filter(|(k, _)| k.starts_with("factord"))
        .collect()
}

/// The environment a service sets (map or `KEY=value` list form).
fn environment(service: &Yaml) -> BTreeMap<String, String> {
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
fn service_argv(service: &Yaml) -> Vec<String> {
    let mut argv = match &service["entrypoint"] {
        Yaml::Null => entrypoint(),
        e => strings(e),
    };
    argv.extend(strings(&service["command"]));
    argv
}

fn flag_value(argv: &[String], flag: &str) -> Option<String> {
    argv.iter()
        .position(|a| a == flag)
        .map(|i| argv[i + 1].clone())
}

/// Where a service's secret `name` is mounted (`/run/secrets/<target or name>`).
fn secret_path(service: &Yaml, name: &str) -> Option<String> {
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

#[test]
fn compose_pins_images_and_gives_every_instance_tokens_health_and_the_shared_volume() {
    let doc = compose();
    // Keys are the compose specification's (a subset of its schema, checked by hand).
    let top = [
        "name", "services", "volumes", "secrets", "networks", "configs",
    ];
    for key in doc
        .as_mapping()
        .unwrap()
        .keys()
        .map(|k| k.as_str().unwrap())
    {
        assert!(
            top.contains(&key) || key.starts_with("x-"),
            "top-level key {key}"
        );
    }
    let zenohd = &doc["services"]["zenohd"];
    let zenoh_image = zenohd["image"].as_str().expect("zenohd image");
    assert_pinned(zenoh_image);
    assert_eq!(
        zenoh_image,
        format!("eclipse/zenoh:{}", locked_version("zenoh")),
        "the router is the version of our zenoh crate"
    );
    assert!(strings(&zenohd["ports"]).contains(&"7447:7447".to_string()));

    let services = factord_services(&doc);
    let names: Vec<&str> = services.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(names, ["factord-1", "factord-2", "factord-3"]);
    let help = serve_help();
    let volume = "factord-state";
    assert!(doc["volumes"].as_mapping().unwrap().contains_key(volume));
    let secret_file = doc["secrets"]["factord_tokens"]["file"]
        .as_str()
        .expect("secret file");
    assert_eq!(secret_file, "./tokens");
    assert!(
        read("docker/.gitignore").lines().any(|l| l == "/tokens"),
        "tokens git-ignored"
    );
    let mut host_ports = Vec::new();
    for (name, service) in &services {
        let known = [
            "build",
            "image",
            "pull_policy",
            "restart",
            "depends_on",
            "environment",
            "secrets",
            "volumes",
            "healthcheck",
            "command",
            "entrypoint",
            "ports",
        ];
        for key in service
            .as_mapping()
            .unwrap()
            .keys()
            .map(|k| k.as_str().unwrap())
        {
            assert!(known.contains(&key), "{name}: key {key}");
        }
        assert_eq!(
            service["build"]["dockerfile"].as_str(),
            Some("docker/Dockerfile")
        );
        assert_eq!(service["build"]["context"].as_str(), Some(".."));
        let image = service["image"].as_str().unwrap();
        assert_eq!(image, format!("factord:{}", crate_version()), "{name}");
        assert_pinned(image);
        assert!(
            service["restart"].as_str().is_some(),
            "{name}: restart policy"
        );
        assert!(
            !service["depends_on"]["zenohd"].is_null(),
            "{name}: depends on zenohd"
        );

        let argv = service_argv(service);
        assert_eq!(argv[..2], ["factord", "serve"], "{name}");
        for flag in argv.iter().filter(|a| a.starts_with("--")) {
            assert!(
                help.contains(flag.as_str()),
                "{name}: factord serve has no {flag}"
            );
        }
        // One shared volume, mounted where the state directory is.
        let state = flag_value(&argv, "--state-dir").expect("--state-dir");
        assert!(
            strings(&service["volumes"]).contains(&format!("{volume}:{state}")),
            "{name}: {volume} on {state}"
        );
        // The fleet: its own id, its HTTP address under its compose name, the router.
        assert!(argv.contains(&"--fleet".to_string()), "{name}: --fleet");
        assert_eq!(
            flag_value(&argv, "--instance-id").as_deref(),
            Some(name.as_str())
        );
        let listen_port = flag_value(&argv, "--listen").unwrap();
        let listen_port = listen_port.rsplit(':').next().unwrap();
        assert_eq!(
            flag_value(&argv, "--advertise-http"),
            Some(format!("http://{name}:{listen_port}"))
        );
        assert_eq!(
            flag_value(&argv, "--zenoh-connect").as_deref(),
            Some("tcp/zenohd:7447")
        );
        // Tokens: the secret, read by serve through FACTORD_TOKENS_FILE; HTTP beyond loopback.
        let tokens = secret_path(service, "factord_tokens").expect("the tokens secret");
        let env = environment(service);
        assert_eq!(env.get("FACTORD_TOKENS_FILE"), Some(&tokens), "{name}");
        for var in env.keys() {
            assert!(
                help.contains(var.as_str()),
                "{name}: factord serve reads no {var}"
            );
        }
        // The health check is `factord health` with the tokens file.
        let test = strings(&service["healthcheck"]["test"]);
        assert_eq!(test[..3], ["CMD", "factord", "health"], "{name}");
        assert_eq!(flag_value(&test, "--token-file"), Some(tokens.clone()));
        for key in ["interval", "timeout", "start_period"] {
            assert!(
                service["healthcheck"][key].as_str().is_some(),
                "{name}: {key}"
            );
        }
        for port in strings(&service["ports"]) {
            let (host, container) = port.split_once(':').unwrap();
            assert_eq!(container, listen_port, "{name}: publishes its HTTP port");
            host_ports.push(host.to_string());
        }
    }
    host_ports.sort();
    host_ports.dedup();
    assert_eq!(host_ports.len(), 3, "each instance on its own host port");
}

// ---- the command lines, run -------------------------------------------------------------------

/// Child processes killed when the test ends, however it ends.
struct Processes(Vec<(String, Child, PathBuf)>);

impl Processes {
    fn logs(&self) -> String {
        self.0
            .iter()
            .map(|(name, _, log)| {
                format!(
                    "--- {name}\n{}",
                    std::fs::read_to_string(log).unwrap_or_default()
                )
            })
            .collect()
    }

    /// SIGTERM to each, then their exit status.
    fn stop(mut self) -> Vec<(String, Option<std::process::ExitStatus>)> {
        let mut out = Vec::new();
        for (name, child, _) in &mut self.0 {
            // SAFETY: kill(2) on our own child's pid.
            unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
            let deadline = Instant::now() + Duration::from_secs(15);
            let status = loop {
                match child.try_wait() {
                    Ok(Some(status)) => break Some(status),
                    _ if Instant::now() > deadline => break None,
                    _ => std::thread::sleep(Duration::from_millis(20)),
                }
            };
            out.push((name.clone(), status));
        }
        out
    }
}

impl Drop for Processes {
    fn drop(&mut self) {
        for (_, child, _) in &mut self.0 {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// The container's names and paths, moved onto this machine.
struct Rewrites(Vec<(String, String)>);

impl Rewrites {
    fn apply(&self, arg: &str) -> String {
        let mut out = arg.to_string();
        for (from, to) in &self.0 {
            out = out.replace(from, to);
        }
        out
    }

    /// Rewrites every argument and checks that no container name or path is left.
    fn argv(&self, argv: &[String], leftovers: &[&str]) -> Vec<String> {
        let out: Vec<String> = argv.iter().map(|a| self.apply(a)).collect();
        for arg in &out {
            for left in leftovers {
                assert!(!arg.contains(left), "{arg}: `{left}` has no rewrite");
            }
        }
        out
    }
}

/// The zenohd service's command, run by our zenoh crate as a router on `port`: only the flags
/// it translates are allowed.
fn zenoh_router(args: &[String], port: u16) -> zenoh::Config {
    let mut config = zenoh::Config::default();
    config.insert_json5("mode", "\"router\"").unwrap();
    let mut args = args.iter();
    while let Some(arg) = args.next() {
        match arg.as_str() {
            "--listen" | "-l" => {
                let endpoint = args.next().expect("--listen value");
                let (proto, _) = endpoint.split_once('/').unwrap();
                let local = format!("[\"{proto}/127.0.0.1:{port}\"]");
                config.insert_json5("listen/endpoints", &local).unwrap();
            }
            "--no-multicast-scouting" => {
                config
                    .insert_json5("scouting/multicast/enabled", "false")
                    .unwrap();
            }
            other => panic!("zenohd flag {other} has no stand-in here"),
        }
    }
    config
}

/// Runs `argv` (a health check) until it exits 0 or `within` passes; the last output.
fn until_healthy(argv: &[String], env: &[(String, String)], within: Duration) -> Output {
    let deadline = Instant::now() + within;
    loop {
        let out = factord()
            .args(&argv[1..])
            .envs(env.iter().cloned())
            .output()
            .unwrap();
        if out.status.success() || Instant::now() > deadline {
            return out;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
}

fn text(out: &Output) -> String {
    format!(
        "exit {:?}\nstdout: {}\nstderr: {}",
        out.status.code(),
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

/// The three factord services as compose starts them, on one shared state directory and
/// through one zenoh router, each healthy by its own health check and by the image's.
#[test]
fn compose_services_start_as_processes_and_pass_their_health_checks() {
    let doc = compose();
    let dir = common::temp_dir("compose");
    let state = dir.join("state");
    let tokens = dir.join("tokens");
    // What a user does first: the example tokens file becomes the secret.
    std::fs::copy(repo().join("docker/tokens.example"), &tokens).unwrap();
    let services = factord_services(&doc);

    let router_port = free_port();
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let router_args = strings(&doc["services"]["zenohd"]["command"]);
    let router = runtime
        .block_on(async { zenoh::open(zenoh_router(&router_args, router_port)).await })
        .expect("the zenohd stand-in starts");

    let http_ports: Vec<u16> = services.iter().map(|_| free_port()).collect();
    let mut rewrites = vec![
        (
            "tcp/zenohd:7447".to_string(),
            format!("tcp/127.0.0.1:{router_port}"),
        ),
        ("/var/lib/factord".into(), state.display().to_string()),
        (
            "/run/secrets/factord_tokens".into(),
            tokens.display().to_string(),
        ),
    ];
    for ((name, _), port) in services.iter().zip(&http_ports) {
        rewrites.push((
            format!("http://{name}:8080"),
            format!("http://127.0.0.1:{port}"),
        ));
    }
    let leftovers = [
        "zenohd",
        "factord-1:",
        "factord-2:",
        "factord-3:",
        "/var/lib",
        "/run/",
    ];

    let mut processes = Processes(Vec::new());
    let mut checks = Vec::new();
    for ((name, service), port) in services.iter().zip(&http_ports) {
        let mut own = Rewrites(rewrites.clone());
        // HTTP stays on every interface, as in the container (so tokens are required), on a
        // free port; zenoh listens on loopback.
        own.0
            .push(("0.0.0.0:8080".into(), format!("0.0.0.0:{port}")));
        own.0.push((
            "tcp/0.0.0.0:7447".into(),
            format!("tcp/127.0.0.1:{}", free_port()),
        ));
        let argv = own.argv(&service_argv(service), &leftovers);
        let env: Vec<(String, String)> = environment(service)
            .into_iter()
            .map(|(k, v)| (k, own.apply(&v)))
            .collect();
        let log = dir.join(format!("{name}.log"));
        let child = factord()
            .args(&argv[1..])
            .envs(env.iter().cloned())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .expect("factord starts");
        processes.0.push((name.clone(), child, log));
        // Docker runs the health check inside the container, where 127.0.0.1:8080 is the
        // server: here FACTORD_URL says where it is.
        let mut check_env = env.clone();
        check_env.push(("FACTORD_URL".into(), format!("http://127.0.0.1:{port}")));
        let test = own.argv(&strings(&service["healthcheck"]["test"]), &leftovers);
        checks.push((name.clone(), test[1..].to_vec(), check_env));
    }
    for (name, test, env) in &checks {
        let out = until_healthy(test, env, Duration::from_secs(30));
        assert!(
            out.status.success(),
            "{name}: {}\n{}",
            text(&out),
            processes.logs()
        );
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(stdout.contains("token accepted"), "{name}: {stdout}");
        // The image's own HEALTHCHECK, with the environment compose gives the container.
        let image_check = healthcheck();
        let out = until_healthy(&image_check, env, Duration::from_secs(5));
        assert!(out.status.success(), "{name}: image check: {}", text(&out));
        assert!(String::from_utf8_lossy(&out.stdout).contains("token accepted"));
        // A token the server does not know is reported, with the reason.
        let mut wrong = env.clone();
        wrong.retain(|(k, _)| k != "FACTORD_TOKENS_FILE");
        wrong.push(("FACTORD_TOKEN".into(), "not-the-token-of-this-fleet".into()));
        let out = until_healthy(&image_check, &wrong, Duration::ZERO);
        assert_eq!(out.status.code(), Some(1), "{name}: {}", text(&out));
        assert!(text(&out).contains("token was refused"), "{}", text(&out));
    }
    // They form one fleet through the router: a session created on one instance is served by
    // every instance's HTTP (the owner's, or forwarded to it at its advertised address).
    let token = std::fs::read_to_string(&tokens).unwrap();
    let token = token
        .lines()
        .find(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .and_then(|l| l.split_whitespace().last())
        .unwrap()
        .to_string();
    let urls: Vec<String> = http_ports
        .iter()
        .map(|p| format!("http://127.0.0.1:{p}"))
        .collect();
    runtime.block_on(async {
        for (i, session) in ["compose-a", "compose-b", "compose-c"].iter().enumerate() {
            let body = format!(r#"{{"session": "{session}", "kind": "pose_graph_2d"}}"#);
            let (status, answer) =
                authorised(&token, "POST", &format!("{}/v1/sessions", urls[i]), &body).await;
            assert_eq!(status, 201, "{session}: {answer}\n{}", processes.logs());
            for url in &urls {
                let url = format!("{url}/v1/sessions/{session}");
                let (status, answer) = authorised(&token, "GET", &url, "").await;
                assert_eq!(status, 200, "{url}: {answer}\n{}", processes.logs());
                assert_eq!(answer["session"], *session, "{answer}");
            }
        }
    });
    for (name, status) in processes.stop() {
        assert!(
            status.is_some_and(|s| s.success()),
            "{name}: stopped with {status:?}"
        );
    }
    runtime.block_on(async { router.close().await }).unwrap();
}

/// A request with the bearer token, repeated while the fleet answers 503 (a session being
/// placed) for at most 20 s; the status and the JSON answer.
async fn authorised(token: &str, method: &str, url: &str, body: &str) -> (u16, serde_json::Value) {
    let client = reqwest::Client::builder()
        .timeout(Duration::from_secs(20))
        .build()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let mut request = client
            .request(method.parse().unwrap(), url)
            .bearer_auth(token);
        if !body.is_empty() {
            request = request
                .header("content-type", "application/json")
                .body(body.to_string());
        }
        let answer = request
            .send()
            .await
            .unwrap_or_else(|e| panic!("{url}: {e}"));
        let status = answer.status().as_u16();
        let text = answer.text().await.unwrap_or_default();
        if status != 503 || Instant::now() > deadline {
            let value = serde_json::from_str(&text).unwrap_or(serde_json::Value::String(text));
            return (status, value);
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Without tokens the image's entrypoint refuses to start (the restart loop compose used to
/// show), naming what is missing; with the tokens file it serves.
#[test]
fn the_entrypoint_needs_tokens_and_starts_with_them() {
    let dir = common::temp_dir("entry");
    let port = free_port();
    let argv = Rewrites(vec![
        (
            "/var/lib/factord".into(),
            dir.join("state").display().to_string(),
        ),
        ("0.0.0.0:8080".into(), format!("0.0.0.0:{port}")),
        (
            "tcp/0.0.0.0:7447".into(),
            format!("tcp/127.0.0.1:{}", free_port()),
        ),
    ])
    .argv(&entrypoint(), &["/var/lib"]);
    let out = factord()
        .args(&argv[1..])
        .env_remove("FACTORD_TOKENS")
        .env_remove("FACTORD_TOKENS_FILE")
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("requires bearer tokens"), "{stderr}");

    let tokens = repo().join("docker/tokens.example");
    let child = factord()
        .args(&argv[1..])
        .env("FACTORD_TOKENS_FILE", &tokens)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let processes = Processes(vec![("entrypoint".into(), child, dir.join("none"))]);
    let env = [
        (
            "FACTORD_URL".to_string(),
            format!("http://127.0.0.1:{port}"),
        ),
        (
            "FACTORD_TOKENS_FILE".to_string(),
            tokens.display().to_string(),
        ),
    ];
    let out = until_healthy(&healthcheck(), &env, Duration::from_secs(30));
    assert!(out.status.success(), "{}", text(&out));
    drop(processes);
}

// ---- factord health against a real server ----------------------------------------------------

fn health(url: &str, args: &[&str], env: &[(&str, &str)]) -> (Option<i32>, String, Duration) {
    let started = Instant::now();
    let out = factord()
        .args(["health", "--url", url])
        .args(args)
        .env_remove("FACTORD_TOKEN")
        .env_remove("FACTORD_TOKENS_FILE")
        .envs(env.iter().copied())
        .output()
        .unwrap();
    let said = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.code(), said, started.elapsed())
}

#[test]
fn health_tells_healthy_refused_token_nothing_listening_and_no_answer_apart() {
    let dir = common::temp_dir("health");
    let tokens = dir.join("tokens");
    std::fs::write(&tokens, "ops a-token-of-at-least-16-chars\n").unwrap();
    let tokens_arg = tokens.display().to_string();
    let server = TestServer::start(&["--no-zenoh", "--tokens-file", &tokens_arg]);
    let url = server.http.clone();

    let (code, said, _) = health(&url, &[], &[]);
    assert_eq!(code, Some(0), "{said}");
    assert!(
        said.starts_with("healthy: factord ") && !said.contains("token"),
        "{said}"
    );
    let (code, said, _) = health(&url, &["--token-file", &tokens_arg], &[]);
    assert_eq!(code, Some(0), "{said}");
    assert!(said.contains("token accepted"), "{said}");
    let (code, said, _) = health(
        &url,
        &[],
        &[("FACTORD_TOKEN", "a-token-of-at-least-16-chars")],
    );
    assert_eq!(code, Some(0), "{said}");
    let (code, said, _) = health(&url, &[], &[("FACTORD_TOKEN", "wrong-token-wrong-token")]);
    assert_eq!(code, Some(1), "{said}");
    assert_eq!(said.lines().count(), 1, "one line: {said}");
    assert!(
        said.contains("unhealthy: the token was refused") && said.contains("not valid"),
        "{said}"
    );
    let (code, said, _) = health(&url, &["--token-file", "/nonexistent/tokens"], &[]);
    assert_eq!(code, Some(1), "{said}");
    assert!(said.contains("/nonexistent/tokens"), "{said}");

    let (status, _) = server.terminate(Duration::from_secs(15));
    assert!(status.is_some_and(|s| s.success()));
    let (code, said, _) = health(&url, &[], &[]);
    assert_eq!(code, Some(1), "{said}");
    assert!(
        said.contains("unhealthy: cannot connect to 127.0.0.1:"),
        "{said}"
    );

    // A listener that takes the connection and never answers: the timeout, not a hang.
    let silent = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let silent_url = format!("http://{}", silent.local_addr().unwrap());
    let (code, said, took) = health(&silent_url, &["--timeout-ms", "400"], &[]);
    assert_eq!(code, Some(1), "{said}");
    assert!(said.contains("no complete answer within 400 ms"), "{said}");
    assert!(took < Duration::from_secs(5), "took {took:?}");
    // A URL the check cannot use.
    let (code, said, _) = health("https://127.0.0.1:1", &[], &[]);
    assert_eq!(code, Some(1), "{said}");
    assert!(said.contains("https"), "{said}");
}
