//! The processes a scenario measures: real `factord serve` release binaries (alone or as a
//! fleet on one shared state directory) on free loopback ports with the journal on, the bare
//! zenoh echo peer (this bench binary again, `__echo`), and what is read from them (peak RSS,
//! HTTP answers, zenoh queries).

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port()
}

/// A fresh directory under the system's temp dir.
pub fn temp_dir(what: &str) -> PathBuf {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos());
    let dir = std::env::temp_dir().join(format!(
        "factord-link-{what}-{}-{nanos}",
        std::process::id()
    ));
    std::fs::create_dir_all(&dir).expect("temp dir");
    dir
}

/// One running `factord serve`.
pub struct Server {
    pub http: String,
    pub zenoh: String,
    pub stderr_path: PathBuf,
    child: Child,
}

impl Server {
    /// `factord serve` on `state_dir`, zenoh listening on `zenoh` (scouting off), connected to
    /// `connect`, plus `extra` flags; waits for its address file `info_name`.
    pub fn start(
        state_dir: &Path,
        info_name: &str,
        zenoh: &str,
        connect: &[String],
        extra: &[&str],
    ) -> Self {
        let info = state_dir.join(info_name);
        let _ = std::fs::remove_file(&info);
        let stderr_path = state_dir.with_extension(format!("{info_name}.stderr"));
        let stderr = std::fs::File::create(&stderr_path).expect("stderr file");
        // FACTORD_LINK_LOG=info: the servers' logs in more detail (kept next to the state
        // directory, `<dir>.<info>.stderr`).
        let log = std::env::var("FACTORD_LINK_LOG").unwrap_or_else(|_| "warn".into());
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_factord"));
        cmd.arg("serve")
            .args(["--listen", "127.0.0.1:0", "--zenoh-listen", zenoh])
            .args(["--zenoh-multicast", "off", "--log", &log])
            .arg("--state-dir")
            .arg(state_dir)
            .args(extra)
            .stdout(Stdio::null())
            .stderr(stderr);
        if !connect.is_empty() {
            cmd.args(["--zenoh-connect", &connect.join(",")]);
        }
        let child = cmd.spawn().expect("factord starts");
        let deadline = Instant::now() + Duration::from_secs(30);
        let http = loop {
            if let Ok(text) = std::fs::read_to_string(&info) {
                if let Ok(v) = serde_json::from_str::<Value>(&text) {
                    break format!("http://{}", v["http"].as_str().expect("http address"));
                }
            }
            assert!(
                Instant::now() < deadline,
                "factord did not start: {}",
                std::fs::read_to_string(&stderr_path).unwrap_or_default()
            );
            std::thread::sleep(Duration::from_millis(20));
        };
        Self {
            http,
            zenoh: zenoh.to_string(),
            stderr_path,
            child,
        }
    }

    /// A lone server with its own state directory.
    pub fn single(extra: &[&str]) -> (Self, PathBuf) {
        let dir = temp_dir("state");
        let zenoh = format!("tcp/127.0.0.1:{}", free_port());
        (Self::start(&dir, "server.json", &zenoh, &[], extra), dir)
    }

    /// `n` fleet instances `f1`..`fn` on one fresh state directory, each connected to those
    /// started before it.
    pub fn fleet(n: usize, extra: &[&str]) -> (Vec<Self>, PathBuf) {
        let dir = temp_dir("fleet");
        let secret = dir.with_extension("fleet-secret");
        std::fs::write(&secret, "the benchmark fleet's secret, 32 bytes or more\n")
            .expect("the fleet secret is written");
        let secret = secret.display().to_string();
        let mut out: Vec<Self> = Vec::new();
        for i in 1..=n {
            let id = format!("f{i}");
            let zenoh = format!("tcp/127.0.0.1:{}", free_port());
            let connect: Vec<String> = out.iter().map(|s| s.zenoh.clone()).collect();
            let mut flags = vec!["--fleet", "--instance-id", id.as_str()];
            flags.extend_from_slice(&["--fleet-secret-file", secret.as_str()]);
            flags.extend_from_slice(extra);
            let info = format!("server-{id}.json");
            out.push(Self::start(&dir, &info, &zenoh, &connect, &flags));
        }
        (out, dir)
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{}", self.http, path)
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    pub fn cpu_seconds(&self) -> f64 {
        cpu_seconds(self.pid())
    }

    /// Peak resident memory so far (`VmHWM`), in KiB.
    pub fn peak_rss_kib(&self) -> u64 {
        proc_status_kib(self.pid(), "VmHWM:")
    }

    pub fn stderr(&self) -> String {
        std::fs::read_to_string(&self.stderr_path).unwrap_or_default()
    }

    /// Lines of the log that are warnings or errors.
    pub fn warnings(&self) -> Vec<String> {
        self.stderr()
            .lines()
            .filter(|l| l.contains("WARN") || l.contains("ERROR") || l.contains("panicked"))
            .map(str::to_string)
            .collect()
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        // SIGTERM first (a clean journal close), SIGKILL after 5 s.
        let _ = Command::new("kill")
            .arg(self.child.id().to_string())
            .status();
        let deadline = Instant::now() + Duration::from_secs(5);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A field of `/proc/<pid>/status` in KiB (0 when unreadable).
pub fn proc_status_kib(pid: u32, field: &str) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .unwrap_or_default()
        .lines()
        .find(|l| l.starts_with(field))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(0)
}

/// CPU time (user + system) a process has used so far, in seconds (`/proc/<pid>/stat`).
pub fn cpu_seconds(pid: u32) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
    // Fields after the command name (which may hold spaces) start at the state, field 3.
    let rest = stat.rsplit_once(')').map_or("", |r| r.1);
    let f: Vec<f64> = rest
        .split_whitespace()
        .map(|v| v.parse().unwrap_or(0.0))
        .collect();
    // SAFETY: sysconf reads a constant of the system.
    let tick = unsafe { libc::sysconf(libc::_SC_CLK_TCK) }.max(1) as f64;
    // utime and stime are fields 14 and 15, i.e. indices 11 and 12 after the state.
    (f.get(11).copied().unwrap_or(0.0) + f.get(12).copied().unwrap_or(0.0)) / tick
}

/// The bare zenoh echo peer: this bench binary run as `__echo <listen>` in its own process.
pub struct EchoPeer {
    pub zenoh: String,
    child: Child,
}

impl EchoPeer {
    pub fn start() -> Self {
        let zenoh = format!("tcp/127.0.0.1:{}", free_port());
        let child = Command::new(std::env::current_exe().expect("own path"))
            .args(["__echo", &zenoh])
            .stdout(Stdio::null())
            .spawn()
            .expect("echo peer starts");
        Self { zenoh, child }
    }

    pub fn peak_rss_kib(&self) -> u64 {
        proc_status_kib(self.child.id(), "VmHWM:")
    }
}

impl Drop for EchoPeer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A zenoh peer on loopback, scouting off, listening nowhere, connected to `endpoints`.
pub async fn zenoh_peer(endpoints: &[&str]) -> zenoh::Session {
    let mut c = zenoh::Config::default();
    let list: Vec<String> = endpoints.iter().map(|e| format!("\"{e}\"")).collect();
    c.insert_json5("mode", "\"peer\"").expect("mode");
    c.insert_json5("scouting/multicast/enabled", "false")
        .expect("scouting");
    c.insert_json5("connect/endpoints", &format!("[{}]", list.join(",")))
        .expect("endpoints");
    zenoh::open(c).await.expect("zenoh peer opens")
}

/// A zenoh query answered (retried until the queryable is known, at most 20 s): the reply's
/// JSON, `Err` with the error reply's.
pub async fn zenoh_get(
    z: &zenoh::Session,
    selector: &str,
    payload: Option<&Value>,
) -> Result<Value, Value> {
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let mut get = z.get(selector).timeout(Duration::from_secs(10));
        if let Some(p) = payload {
            get = get.payload(p.to_string());
        }
        let replies = get.await.expect("query sent");
        if let Ok(reply) = replies.recv_async().await {
            let parse = |b: &[u8]| serde_json::from_slice(b).unwrap_or(Value::Null);
            return match reply.result() {
                Ok(sample) => Ok(parse(&sample.payload().to_bytes())),
                Err(err) => Err(parse(&err.payload().to_bytes())),
            };
        }
        assert!(Instant::now() < deadline, "no reply to {selector}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// `GET url` → (status, JSON).
pub async fn http_get(c: &reqwest::Client, url: &str) -> (u16, Value) {
    let r = c
        .get(url)
        .send()
        .await
        .unwrap_or_else(|e| panic!("{url}: {e}"));
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

/// `POST url` with a JSON body → (status, JSON).
pub async fn http_post(c: &reqwest::Client, url: &str, body: &Value) -> (u16, Value) {
    let r = c
        .post(url)
        .header("content-type", "application/json")
        .body(body.to_string())
        .send()
        .await
        .unwrap_or_else(|e| panic!("{url}: {e}"));
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

/// The server's Prometheus text (`GET /metrics`): lines matching any of `names`, histogram
/// buckets left out.
pub async fn metrics(c: &reqwest::Client, s: &Server, names: &[&str]) -> Vec<String> {
    let Ok(r) = c.get(s.url("/metrics")).send().await else {
        return Vec::new();
    };
    let text = r.text().await.unwrap_or_default();
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.contains("_bucket"))
        .filter(|l| names.iter().any(|n| l.contains(n)))
        .map(str::to_string)
        .collect()
}

/// `perf record -g` of a server while a stream runs, when `FACTORD_LINK_PERF=<file>` is set
/// (the profile of where the server's time goes); stopped (SIGINT) when dropped.
pub struct Perf(Option<Child>);

impl Perf {
    pub fn attach(pid: u32) -> Self {
        let Some(out) = std::env::var_os("FACTORD_LINK_PERF") else {
            return Self(None);
        };
        let child = Command::new("perf")
            .args(["record", "-F", "999", "-g", "-p", &pid.to_string(), "-o"])
            .arg(out)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .ok();
        std::thread::sleep(Duration::from_millis(300));
        Self(child)
    }
}

impl Drop for Perf {
    fn drop(&mut self) {
        if let Some(mut child) = self.0.take() {
            let _ = Command::new("kill")
                .args(["-INT", &child.id().to_string()])
                .status();
            let _ = child.wait();
        }
    }
}

/// The cumulative bucket lines `le` of histogram `name` from `GET /metrics`.
pub async fn metric_buckets(
    c: &reqwest::Client,
    s: &Server,
    name: &str,
    le: &[&str],
) -> Vec<String> {
    let Ok(r) = c.get(s.url("/metrics")).send().await else {
        return Vec::new();
    };
    let text = r.text().await.unwrap_or_default();
    text.lines()
        .filter(|l| l.starts_with(&format!("{name}_bucket")))
        .filter(|l| le.iter().any(|v| l.contains(&format!("le=\"{v}\""))))
        .map(str::to_string)
        .collect()
}
