//! The container files, checked without a container engine (none runs here): the Dockerfile and
//! docker/compose.yaml are read and held to the rules they promise (pinned tags, a dependency
//! layer, a non-root user, health checks, tokens, one shared volume). `tests/tools/docker_run.rs` runs
//! the command lines they would run.

use crate::common;

use std::path::Path;
use std::process::Command;

use common::docker::*;

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
