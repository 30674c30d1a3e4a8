//! Starts the real `factord serve` binary on free loopback ports (HTTP and zenoh, scouting off)
//! and talks to it over real sockets.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use serde_json::{json, Value};

pub struct TestServer {
    pub http: String,
    pub zenoh: String,
    pub state_dir: PathBuf,
    stderr_path: PathBuf,
    child: Option<Child>,
}

pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port()
}

impl TestServer {
    /// `factord serve` with its own state directory, plus `extra` flags.
    pub fn start(extra: &[&str]) -> Self {
        Self::start_with_env(extra, &[])
    }

    pub fn start_with_env(extra: &[&str], env: &[(&str, &str)]) -> Self {
        Self::start_at(&super::temp_dir("server"), extra, env)
    }

    /// `factord serve` on an existing state directory (a restart after a crash).
    pub fn start_at(state_dir: &Path, extra: &[&str], env: &[(&str, &str)]) -> Self {
        Self::start_with(state_dir, extra, env, |_| {})
    }

    /// `factord serve` allowed at most `files` open files (soft and hard limit), as a server
    /// on a machine with a small limit would be.
    pub fn start_with_file_limit(extra: &[&str], files: u64) -> Self {
        Self::start_with(&super::temp_dir("server"), extra, &[], move |cmd| {
            use std::os::unix::process::CommandExt;
            let limit = libc::rlimit {
                rlim_cur: files as libc::rlim_t,
                rlim_max: files as libc::rlim_t,
            };
            // SAFETY: setrlimit is async-signal-safe and touches only the struct passed in.
            unsafe {
                cmd.pre_exec(move || match libc::setrlimit(libc::RLIMIT_NOFILE, &limit) {
                    0 => Ok(()),
                    _ => Err(std::io::Error::last_os_error()),
                });
            }
        })
    }

    /// Starts the server; when its zenoh port was taken between [`free_port`] and the server's
    /// bind (another test's process got it), tries again on a new port.
    fn start_with(
        state_dir: &Path,
        extra: &[&str],
        env: &[(&str, &str)],
        configure: impl Fn(&mut Command),
    ) -> Self {
        const ATTEMPTS: usize = 3;
        let state_dir = state_dir.to_path_buf();
        let stderr_path = state_dir.with_extension("stderr");
        for attempt in 1..=ATTEMPTS {
            // A killed server leaves its address file behind; wait for the new one.
            let _ = std::fs::remove_file(state_dir.join("server.json"));
            let zenoh = format!("tcp/127.0.0.1:{}", free_port());
            let stderr = std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(&stderr_path)
                .expect("stderr file");
            let logged_before = stderr.metadata().map_or(0, |m| m.len() as usize);
            let mut cmd = server_command();
            cmd.arg("serve");
            if !extra.contains(&"--listen") {
                cmd.args(["--listen", "127.0.0.1:0"]);
            }
            cmd.args(["--zenoh-listen", &zenoh])
                .arg("--state-dir")
                .arg(&state_dir)
                .args(["--zenoh-multicast", "off"])
                .args(extra)
                .stdout(Stdio::null())
                .stderr(stderr);
            for (k, v) in env {
                cmd.env(k, v);
            }
            configure(&mut cmd);
            let mut child = cmd.spawn().expect("factord starts");
            match started(&state_dir.join("server.json"), &mut child) {
                Some(http) => {
                    return Self {
                        http,
                        zenoh,
                        state_dir,
                        stderr_path,
                        child: Some(child),
                    }
                }
                None => {
                    let _ = child.kill();
                    let _ = child.wait();
                    let log = read(&stderr_path);
                    let port_taken = log
                        .get(logged_before..)
                        .is_some_and(|new| new.contains("Address already in use"));
                    assert!(
                        port_taken && attempt < ATTEMPTS,
                        "server did not start: {log}"
                    );
                }
            }
        }
        unreachable!("the last attempt returns or panics")
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{}", self.http, path)
    }

    pub fn stderr(&self) -> String {
        read(&self.stderr_path)
    }

    pub fn pid(&self) -> u32 {
        self.child.as_ref().expect("running").id()
    }

    /// The server's peak resident set (VmHWM), in bytes.
    pub fn peak_rss(&self) -> u64 {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.pid())).unwrap();
        let line = status
            .lines()
            .find(|l| l.starts_with("VmHWM:"))
            .expect("VmHWM");
        let kib: u64 = line.split_whitespace().nth(1).unwrap().parse().unwrap();
        kib << 10
    }

    /// SIGTERM, then wait (at most `timeout`); returns the exit status and the log.
    pub fn terminate(mut self, timeout: Duration) -> (Option<ExitStatus>, String) {
        let mut child = self.child.take().expect("running");
        let _ = Command::new("kill").arg(child.id().to_string()).status();
        let deadline = Instant::now() + timeout;
        let status = loop {
            if let Ok(Some(status)) = child.try_wait() {
                break Some(status);
            }
            if Instant::now() > deadline {
                let _ = child.kill();
                let _ = child.wait();
                break None;
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        (status, read(&self.stderr_path))
    }

    /// SIGKILL: no shutdown at all, as in a crash or power cut of the process.
    pub fn kill(mut self) -> String {
        let mut child = self.child.take().expect("running");
        let _ = child.kill();
        let _ = child.wait();
        read(&self.stderr_path)
    }

    /// Asserts the server never panicked.
    pub fn assert_no_panic(&self) {
        let log = self.stderr();
        assert!(!log.contains("panicked"), "server panicked:\n{log}");
    }
}

impl Drop for TestServer {
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_default()
}

pub fn client() -> reqwest::Client {
    reqwest::Client::builder()
        .timeout(Duration::from_secs(120))
        .build()
        .expect("client")
}

/// Sends `body` (JSON) and returns the status and the parsed JSON answer.
pub async fn send(
    client: &reqwest::Client,
    method: reqwest::Method,
    url: &str,
    body: Option<&Value>,
) -> (u16, Value) {
    let mut req = client.request(method, url);
    if let Some(b) = body {
        req = req
            .header("content-type", "application/json")
            .body(b.to_string());
    }
    let resp = req
        .send()
        .await
        .unwrap_or_else(|e| panic!("{url}: request failed: {e:?}"));
    let status = resp.status().as_u16();
    let text = resp.text().await.expect("body");
    let value = serde_json::from_str(&text).unwrap_or(Value::String(text));
    (status, value)
}

/// Posts a body as is (a graph file, deliberately broken JSON) and parses the JSON answer.
/// Graph files go to `/v1/jobs` as text; everything else is sent as JSON, which the JSON
/// routes require.
pub async fn post_raw(
    client: &reqwest::Client,
    url: &str,
    body: impl Into<reqwest::Body>,
) -> (u16, Value) {
    let content_type = if url.contains("/v1/jobs") {
        "text/plain"
    } else {
        "application/json"
    };
    let resp = client
        .post(url)
        .header("content-type", content_type)
        .body(body)
        .send()
        .await
        .unwrap_or_else(|e| panic!("{url}: request failed: {e:?}"));
    let status = resp.status().as_u16();
    let text = resp.text().await.expect("body");
    (
        status,
        serde_json::from_str(&text).unwrap_or(Value::String(text)),
    )
}

pub async fn post(client: &reqwest::Client, url: &str, body: &Value) -> (u16, Value) {
    send(client, reqwest::Method::POST, url, Some(body)).await
}

/// Creates a session (`POST /v1/sessions` with `body`), asserting 201; returns its info.
pub async fn create(client: &reqwest::Client, s: &TestServer, body: &Value) -> Value {
    let (status, v) = post(client, &s.url("/v1/sessions"), body).await;
    assert_eq!(status, 201, "{body}: {v}");
    v
}

pub async fn get(client: &reqwest::Client, url: &str) -> (u16, Value) {
    send(client, reqwest::Method::GET, url, None).await
}

/// `DELETE /v1/sessions/{name}`: the status and the JSON answer.
pub async fn delete_session(client: &reqwest::Client, s: &TestServer, name: &str) -> (u16, Value) {
    let url = s.url(&format!("/v1/sessions/{name}"));
    send(client, reqwest::Method::DELETE, &url, None).await
}

/// A g2o pose graph (2D or 3D) as streaming batches: pose k with every edge whose later end is
/// k. A pose with an odometry edge from k−1 is sent without a value (the server predicts it).
pub fn g2o_batches(text: &str) -> Vec<Value> {
    /// (from, to, factor type, measurement, information upper triangle)
    type Edge<'a> = (u64, u64, &'a str, Vec<f64>, Vec<f64>);
    let mut vertices: Vec<(u64, &str, Vec<f64>)> = Vec::new();
    let mut edges: Vec<Edge> = Vec::new();
    for line in text.lines() {
        let t: Vec<&str> = line.split_whitespace().collect();
        let nums =
            |from: usize| -> Vec<f64> { t[from..].iter().map(|v| v.parse().unwrap()).collect() };
        match t.first() {
            Some(&"VERTEX_SE2") => vertices.push((t[1].parse().unwrap(), "se2", nums(2))),
            Some(&"VERTEX_SE3:QUAT") => vertices.push((t[1].parse().unwrap(), "se3", nums(2))),
            Some(&"EDGE_SE2") => {
                let n = nums(3);
                edges.push((
                    t[1].parse().unwrap(),
                    t[2].parse().unwrap(),
                    "between_se2",
                    n[..3].to_vec(),
                    n[3..].to_vec(),
                ));
            }
            Some(&"EDGE_SE3:QUAT") => {
                let n = nums(3);
                // g2o's rotation error is half the angle: Ω' = D Ω D, D = diag(1,1,1,½,½,½).
                let mut info = n[7..].to_vec();
                let mut k = 0;
                for i in 0..6 {
                    for j in i..6 {
                        let d = |r: usize| if r < 3 { 1.0 } else { 0.5 };
                        info[k] *= d(i) * d(j);
                        k += 1;
                    }
                }
                edges.push((
                    t[1].parse().unwrap(),
                    t[2].parse().unwrap(),
                    "between_se3",
                    n[..7].to_vec(),
                    info,
                ));
            }
            _ => {}
        }
    }
    vertices.sort_by_key(|v| v.0);
    let mut by_later: std::collections::BTreeMap<u64, Vec<Value>> = Default::default();
    let mut odometry = std::collections::HashSet::new();
    for (a, b, ty, z, info) in &edges {
        if a + 1 == *b {
            odometry.insert(*b);
        }
        by_later.entry(*a.max(b)).or_default().push(json!({
            "type": ty, "keys": [a, b], "measurement": z, "information": info
        }));
    }
    vertices
        .iter()
        .enumerate()
        .map(|(i, (key, kind, value))| {
            let variable = if i > 0 && odometry.contains(key) {
                json!({"key": key, "kind": kind})
            } else {
                json!({"key": key, "kind": kind, "value": value})
            };
            json!({
                "variables": [variable],
                "factors": by_later.remove(key).unwrap_or_default(),
            })
        })
        .collect()
}

/// The HTTP URL `child` writes to `info` (its `server.json`) once started, waited for up to
/// 20 s; `None` when it exits first or does not start in time.
fn started(info: &Path, child: &mut Child) -> Option<String> {
    let deadline = Instant::now() + Duration::from_secs(20);
    while Instant::now() < deadline {
        if let Ok(text) = std::fs::read_to_string(info) {
            if let Ok(v) = serde_json::from_str::<Value>(&text) {
                return Some(format!(
                    "http://{}",
                    v["http"].as_str().expect("http address")
                ));
            }
        }
        if matches!(child.try_wait(), Ok(Some(_))) {
            return None;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    None
}

/// Every JSON sample published on `key` from now on, in arrival order, for as long as the
/// returned subscriber lives.
pub async fn json_samples(
    z: &zenoh::Session,
    key: &str,
) -> (
    zenoh::pubsub::Subscriber<()>,
    std::sync::mpsc::Receiver<Value>,
) {
    let (tx, rx) = std::sync::mpsc::channel::<Value>();
    let tx = std::sync::Mutex::new(tx);
    let subscriber = z
        .declare_subscriber(key.to_string())
        .callback(move |sample| {
            let v = serde_json::from_slice(&sample.payload().to_bytes()).expect("JSON samples");
            let _ = tx.lock().expect("not poisoned").send(v);
        })
        .await
        .expect("subscriber declared");
    (subscriber, rx)
}

/// A zenoh peer on loopback connected to `endpoint`, scouting off.
pub async fn zenoh_peer(endpoint: &str) -> zenoh::Session {
    zenoh_session("peer", "connect", endpoint).await
}

/// A zenoh session in `mode` (`peer`, `client`, `router`), multicast scouting off, that
/// `connects` to or `listen`s on `endpoint`.
pub async fn zenoh_session(mode: &str, endpoints: &str, endpoint: &str) -> zenoh::Session {
    let mut c = zenoh::Config::default();
    c.insert_json5("mode", &format!("\"{mode}\"")).unwrap();
    c.insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    c.insert_json5(
        &format!("{endpoints}/endpoints"),
        &format!("[\"{endpoint}\"]"),
    )
    .unwrap();
    zenoh::open(c)
        .await
        .unwrap_or_else(|e| panic!("zenoh {mode} on {endpoint} opens: {e}"))
}

/// The ROS 2 nodes of `domain` as `ros2 node list` finds them, as (zenoh id, node name): from
/// the rmw_zenoh node liveliness tokens (`@ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/%/%/<name>`)
/// alive now.
pub async fn ros_nodes(z: &zenoh::Session, domain: u32) -> Vec<(String, String)> {
    let replies = z
        .liveliness()
        .get(format!("@ros2_lv/{domain}/**"))
        .await
        .expect("a liveliness query");
    let mut nodes = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result() {
            let parts: Vec<&str> = sample.key_expr().as_str().split('/').collect();
            if let (Some(zid), Some(&"NN"), Some(name)) = (parts.get(2), parts.get(5), parts.last())
            {
                nodes.push((zid.to_string(), name.to_string()));
            }
        }
    }
    nodes
}

/// The zenoh ids of the peers holding ROS node `name`.
pub fn holders(nodes: &[(String, String)], name: &str) -> Vec<String> {
    nodes
        .iter()
        .filter(|(_, n)| n == name)
        .map(|(zid, _)| zid.clone())
        .collect()
}

/// Waits up to `within` for `done(ros_nodes)`; the last list either way.
pub async fn ros_nodes_until(
    z: &zenoh::Session,
    domain: u32,
    within: Duration,
    done: impl Fn(&[(String, String)]) -> bool,
) -> Vec<(String, String)> {
    let deadline = Instant::now() + within;
    loop {
        let nodes = ros_nodes(z, domain).await;
        if done(&nodes) || Instant::now() > deadline {
            return nodes;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// A zenoh query, retried until the server's queryable is known to this peer.
pub async fn zenoh_get(
    z: &zenoh::Session,
    selector: &str,
    payload: Option<&Value>,
) -> Result<Value, Value> {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let mut get = z.get(selector).timeout(Duration::from_secs(10));
        if let Some(p) = payload {
            get = get.payload(p.to_string());
        }
        let replies = get.await.expect("query sent");
        if let Ok(reply) = replies.recv_async().await {
            let parse = |bytes: &[u8]| -> Value {
                serde_json::from_slice(bytes).unwrap_or_else(|e| {
                    panic!(
                        "{selector}: reply is not JSON ({e}): {:?}",
                        String::from_utf8_lossy(bytes)
                    )
                })
            };
            return match reply.result() {
                Ok(sample) => Ok(parse(&sample.payload().to_bytes())),
                Err(err) => Err(parse(&err.payload().to_bytes())),
            };
        }
        assert!(Instant::now() < deadline, "no reply to {selector}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Solver options no tolerance can stop: a solve runs until cancelled (or 100 000 iterations).
fn endless_options() -> Value {
    json!({"max_iterations": 100000, "function_tolerance": 0.0, "gradient_tolerance": 0.0,
           "parameter_tolerance": 0.0, "method": "gauss_newton", "initialization": "none"})
}

/// Creates session `name` (manual policy, endless options) holding a 1500-pose synthetic graph,
/// asks for a solve and returns once it is running.
pub async fn start_long_solve(c: &reqwest::Client, s: &TestServer, name: &str) {
    let request = json!({"session": name, "kind": "pose_graph_2d", "options": endless_options(),
        "auto_optimize": {"policy": "manual"}});
    create(c, s, &request).await;
    let (mut variables, mut factors) = (Vec::new(), Vec::new());
    for b in g2o_batches(&super::synthetic_manhattan(1500, 7)) {
        variables.extend(b["variables"].as_array().unwrap().clone());
        factors.extend(b["factors"].as_array().unwrap().clone());
    }
    let all = json!({"variables": variables, "factors": factors});
    let (status, v) = post(c, &s.url(&format!("/v1/sessions/{name}/batches")), &all).await;
    assert_eq!(status, 200, "{v}");
    let url = s.url(&format!("/v1/sessions/{name}/optimize"));
    assert_eq!(post(c, &url, &json!({})).await.0, 202);
    let deadline = Instant::now() + Duration::from_secs(10);
    while get(c, &s.url(&format!("/v1/sessions/{name}"))).await.1["solving"] != true {
        assert!(Instant::now() < deadline, "the solve did not start");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// Polls the session's statistics until it is no longer recovering; returns them and how long
/// that took since `since`.
pub async fn recovered(
    c: &reqwest::Client,
    s: &TestServer,
    name: &str,
    since: Instant,
) -> (Value, f64) {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let (status, v) = get(c, &s.url(&format!("/v1/sessions/{name}"))).await;
        if status == 200 && v["recovering"] == false {
            return (v, since.elapsed().as_secs_f64());
        }
        assert!(
            Instant::now() < deadline,
            "{name} still recovering: {status} {v}"
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// `factord serve` without zenoh or journal, with `limits` (a JSON object) from a config file.
pub fn start_with_limits(limits: &Value) -> TestServer {
    let dir = super::temp_dir("limits");
    let config = dir.join("config.json");
    std::fs::write(&config, json!({ "limits": limits }).to_string()).expect("config written");
    TestServer::start(&[
        "--no-zenoh",
        "--no-journal",
        "--config",
        config.to_str().unwrap(),
    ])
}

/// Posts a batch job (`query`: its query string) and waits at most `wait` for the answer:
/// its status, its JSON and the wall time. Waiting longer would only measure how late a job
/// that ignores its limit is, so no answer in time is a failure.
pub async fn post_job_within(
    s: &TestServer,
    query: &str,
    body: String,
    wait: Duration,
) -> (u16, Value, Duration) {
    let c = reqwest::Client::builder().timeout(wait).build().unwrap();
    let start = Instant::now();
    let answer = c
        .post(s.url(&format!("/v1/jobs?{query}")))
        .body(body)
        .send()
        .await
        .expect("the job answers in time");
    let status = answer.status().as_u16();
    let v: Value = answer.json().await.expect("a JSON answer");
    (status, v, start.elapsed())
}

/// The server's command: the binary, or under `FACTORD_SERVER_WRAPPER` (whitespace-separated,
/// e.g. `heaptrack -o /tmp/serve`) the binary run by that profiler, for benchmarks that look
/// into the server's memory.
fn server_command() -> Command {
    let binary = env!("CARGO_BIN_EXE_factord");
    let wrapper = std::env::var("FACTORD_SERVER_WRAPPER").unwrap_or_default();
    let mut words = wrapper.split_whitespace();
    match words.next() {
        None => Command::new(binary),
        Some(program) => {
            let mut cmd = Command::new(program);
            cmd.args(words).arg(binary);
            cmd
        }
    }
}
