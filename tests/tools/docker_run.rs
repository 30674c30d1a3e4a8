//! The container files' command lines, run without a container engine (none runs here): each
//! compose service's `factord serve` as a real process, with paths moved to a temporary
//! directory and ports to free ones, a zenoh router from our zenoh crate standing in for zenohd,
//! and the services' health checks against them; the image's entrypoint with and without
//! tokens; and `factord health` telling its failures apart.

use crate::common;

use std::path::PathBuf;
use std::process::{Child, Output, Stdio};
use std::time::{Duration, Instant};

use common::docker::*;
use common::server::{free_port, TestServer};

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
    // And the fleet's secret, as the compose file's header says to make it.
    let fleet_secret = dir.join("fleet-secret");
    std::fs::write(
        &fleet_secret,
        "a random secret of forty-eight bytes, base64'd\n",
    )
    .unwrap();
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
        (
            "/run/secrets/factord_fleet_secret".into(),
            fleet_secret.display().to_string(),
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
    std::fs::write(
        &tokens,
        "ops a-token-of-at-least-16-chars\ntenant a-tenants-token-16-chars\n",
    )
    .unwrap();
    let tokens_arg = tokens.display().to_string();
    let server = TestServer::start(&[
        "--no-zenoh",
        "--tokens-file",
        &tokens_arg,
        "--operators",
        "ops",
    ]);
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
    // A tenant's token is valid, though /metrics is the operator's (403 there).
    let (code, said, _) = health(&url, &[], &[("FACTORD_TOKEN", "a-tenants-token-16-chars")]);
    assert_eq!(code, Some(0), "{said}");
    assert!(said.contains("token accepted (not an operator"), "{said}");
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
