//! A fleet of real `factord serve --fleet` processes on loopback: distinct HTTP and zenoh
//! ports, one shared state directory, each instance connected over zenoh as its [`Wiring`]
//! says (by default to those started before it; zenoh's gossip completes the mesh).
//! Instances can be killed (-9) and restarted.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

use super::server::free_port;

pub struct Instance {
    pub id: String,
    pub http: String,
    pub zenoh: String,
    pub pid: u32,
    stderr_path: PathBuf,
    child: Child,
}

impl Instance {
    pub fn url(&self, path: &str) -> String {
        format!("{}{}", self.http, path)
    }

    pub fn stderr(&self) -> String {
        std::fs::read_to_string(&self.stderr_path).unwrap_or_default()
    }
}

impl Drop for Instance {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Whom each instance connects to over zenoh.
#[derive(Clone, Debug)]
pub enum Wiring {
    /// Every instance running when it starts (peers; gossip completes the mesh).
    Mesh,
    /// The guide's fleet (docs/guide/fleets.md): the first instance listens, every other connects
    /// to it alone.
    Star,
    /// Instance `i` connects to `endpoints[i]` only: routers', or other instances' endpoints
    /// chosen in advance with [`Fleet::zenoh_endpoints`] and given to [`Fleet::start_on`].
    Explicit(Vec<Vec<String>>),
}

pub struct Fleet {
    pub state_dir: PathBuf,
    /// By index; `None` while killed.
    pub instances: Vec<Option<Instance>>,
    ids: Vec<String>,
    zenoh: Vec<String>,
    extra: Vec<String>,
    wiring: Wiring,
}

impl Fleet {
    /// `n` instances `f1`..`fn` on a fresh state directory, started one after the other, plus
    /// `extra` flags for each.
    pub fn start(n: usize, extra: &[&str]) -> Self {
        Self::start_wired(n, extra, Wiring::Mesh)
    }

    /// As [`Fleet::start`], connected as `wiring` says.
    pub fn start_wired(n: usize, extra: &[&str], wiring: Wiring) -> Self {
        Self::start_on(Self::zenoh_endpoints(n), extra, wiring)
    }

    /// `n` fresh zenoh endpoints on loopback, one per instance: for an [`Wiring::Explicit`]
    /// that names instances, pass the same ones to [`Fleet::start_on`].
    pub fn zenoh_endpoints(n: usize) -> Vec<String> {
        (0..n)
            .map(|_| format!("tcp/127.0.0.1:{}", free_port()))
            .collect()
    }

    /// Instances listening on `zenoh` (one endpoint each), connected as `wiring` says.
    pub fn start_on(zenoh: Vec<String>, extra: &[&str], wiring: Wiring) -> Self {
        let n = zenoh.len();
        let state_dir = super::temp_dir("fleet-state");
        let mut fleet = Self {
            state_dir,
            instances: (0..n).map(|_| None).collect(),
            ids: (1..=n).map(|i| format!("f{i}")).collect(),
            zenoh,
            extra: extra.iter().map(|s| s.to_string()).collect(),
            wiring,
        };
        for i in 0..n {
            // Appended to across restarts; one left by an earlier run with this process id is
            // not this fleet's.
            let _ = std::fs::remove_file(fleet.stderr_path(i));
            fleet.start_first_time(i);
        }
        fleet
    }

    /// Starts instance `i` for the first time. Its zenoh port was picked free before any
    /// instance started, and a test running beside may have taken it since: then (unless the
    /// test named the endpoints) it gets a fresh one, which no running instance knows yet
    /// (each connects only to those started before it, or to the hub, started first).
    fn start_first_time(&mut self, i: usize) {
        for _ in 0..3 {
            match self.try_start_instance(i) {
                Ok(()) => return,
                Err(log)
                    if log.contains("Address already in use")
                        && !matches!(self.wiring, Wiring::Explicit(_)) =>
                {
                    self.zenoh[i] = format!("tcp/127.0.0.1:{}", free_port());
                }
                Err(log) => panic!("instance {} did not start: {log}", self.ids[i]),
            }
        }
        panic!("instance {}: no free zenoh port in 3 tries", self.ids[i]);
    }

    /// The fleet's shared secret (beside the state directory), written on first use.
    pub fn secret_file(&self) -> PathBuf {
        let path = self.state_dir.with_extension("fleet-secret");
        if !path.exists() {
            std::fs::write(&path, format!("secret of {}\n", path.display())).unwrap();
        }
        path
    }

    /// Where instance `i` logs (beside the state directory).
    fn stderr_path(&self, i: usize) -> PathBuf {
        self.state_dir
            .with_extension(format!("{}.stderr", self.ids[i]))
    }

    /// The zenoh endpoints instance `i` connects to.
    fn connect_of(&self, i: usize) -> Vec<String> {
        match &self.wiring {
            Wiring::Mesh => (0..self.ids.len())
                .filter(|&j| j != i && self.instances[j].is_some())
                .map(|j| self.zenoh[j].clone())
                .collect(),
            Wiring::Star if i == 0 => Vec::new(),
            Wiring::Star => vec![self.zenoh[0].clone()],
            Wiring::Explicit(endpoints) => endpoints[i].clone(),
        }
    }

    /// Starts (or restarts) instance `i`, connected as the fleet's [`Wiring`] says.
    pub fn start_instance(&mut self, i: usize) {
        if let Err(log) = self.try_start_instance(i) {
            panic!("instance {} did not start: {log}", self.ids[i]);
        }
    }

    /// Starts instance `i`; its log when it exits (or does not serve within 20 s) instead.
    fn try_start_instance(&mut self, i: usize) -> Result<(), String> {
        let id = self.ids[i].clone();
        let info = self.state_dir.join(format!("server-{id}.json"));
        let _ = std::fs::remove_file(&info);
        let stderr_path = self.stderr_path(i);
        let stderr = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&stderr_path)
            .expect("stderr file");
        let connect = self.connect_of(i);
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_factord"));
        cmd.arg("serve")
            .args(["--fleet", "--instance-id", &id])
            .env("FACTORD_FLEET_SECRET_FILE", self.secret_file())
            .args(["--listen", "127.0.0.1:0"])
            .args(["--zenoh-listen", &self.zenoh[i]])
            .args(["--zenoh-multicast", "off"])
            .arg("--state-dir")
            .arg(&self.state_dir)
            .args(&self.extra)
            .stdout(Stdio::null())
            .stderr(stderr);
        if !connect.is_empty() {
            cmd.args(["--zenoh-connect", &connect.join(",")]);
        }
        // This start's own lines of the log (it is appended to across restarts).
        let logged_before = std::fs::metadata(&stderr_path).map_or(0, |m| m.len() as usize);
        let mut child = cmd.spawn().expect("factord starts");
        let deadline = Instant::now() + Duration::from_secs(20);
        let http = loop {
            if let Ok(text) = std::fs::read_to_string(&info) {
                if let Ok(v) = serde_json::from_str::<Value>(&text) {
                    break format!("http://{}", v["http"].as_str().expect("http address"));
                }
            }
            // Exited before it served: its log says why.
            if child.try_wait().ok().flatten().is_some() || Instant::now() > deadline {
                let _ = child.kill();
                let _ = child.wait();
                let log = read(&stderr_path);
                return Err(log.get(logged_before..).unwrap_or(&log).to_string());
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        self.instances[i] = Some(Instance {
            id,
            http,
            zenoh: self.zenoh[i].clone(),
            pid: child.id(),
            stderr_path,
            child,
        });
        Ok(())
    }

    pub fn instance(&self, i: usize) -> &Instance {
        self.instances[i].as_ref().expect("instance running")
    }

    /// SIGKILL instance `i`; returns its log.
    pub fn kill(&mut self, i: usize) -> String {
        let mut instance = self.instances[i].take().expect("instance running");
        let _ = instance.child.kill();
        let _ = instance.child.wait();
        instance.stderr()
    }

    /// The indices of the running instances.
    pub fn running(&self) -> Vec<usize> {
        (0..self.ids.len())
            .filter(|&i| self.instances[i].is_some())
            .collect()
    }

    pub fn id(&self, i: usize) -> &str {
        &self.ids[i]
    }

    /// The index of the instance that owns `session` among the running ones.
    pub fn owner(&self, session: &str) -> usize {
        let running = self.running();
        let owner = factord::service::placement::owner(
            session,
            running.iter().map(|&i| self.ids[i].as_str()),
        )
        .expect("an instance is running");
        self.ids.iter().position(|id| id == owner).unwrap()
    }

    /// Waits until every running instance has settled and knows every other one's URL.
    pub async fn wait_settled(&self, z: &zenoh::Session) {
        let deadline = Instant::now() + Duration::from_secs(20);
        let expected: Vec<&str> = self
            .running()
            .iter()
            .map(|&i| self.ids[i].as_str())
            .collect();
        loop {
            let infos = infos(z).await;
            let ready = expected.iter().all(|id| {
                infos.iter().any(|info| {
                    info["instance"] == *id
                        && info["settled"] == true
                        && expected
                            .iter()
                            .all(|other| info["live"][*other].is_string())
                        && info["live"]
                            .as_object()
                            .is_some_and(|l| l.len() == expected.len())
                })
            });
            if ready {
                return;
            }
            assert!(
                Instant::now() < deadline,
                "the fleet did not settle: {infos:?}"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    /// Every running instance's log, for failure messages.
    pub fn logs(&self) -> String {
        self.running()
            .iter()
            .map(|&i| format!("--- {} ---\n{}", self.ids[i], self.instance(i).stderr()))
            .collect()
    }
}

/// Every reply to `payload` on `key`, each as it came (no consolidation): the JSON of a reply,
/// or of an error reply.
pub async fn zenoh_replies(
    z: &zenoh::Session,
    key: &str,
    payload: &Value,
) -> Vec<Result<Value, Value>> {
    let replies = z
        .get(key)
        .payload(payload.to_string())
        .consolidation(zenoh::query::ConsolidationMode::None)
        .timeout(Duration::from_secs(10))
        .await
        .expect("query sent");
    let mut out = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        out.push(match reply.result() {
            Ok(s) => Ok(serde_json::from_slice(&s.payload().to_bytes()).unwrap()),
            Err(e) => Err(serde_json::from_slice(&e.payload().to_bytes()).unwrap()),
        });
    }
    out
}

/// Every instance's `info` (zenoh `factord/@fleet/*/info`).
pub async fn infos(z: &zenoh::Session) -> Vec<Value> {
    let replies = z
        .get("factord/@fleet/*/info")
        .target(zenoh::query::QueryTarget::All)
        .consolidation(zenoh::query::ConsolidationMode::None)
        .timeout(Duration::from_secs(2))
        .await
        .expect("query sent");
    let mut out = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result() {
            if let Ok(v) = serde_json::from_slice(&sample.payload().to_bytes()) {
                out.push(v);
            }
        }
    }
    out
}

/// The instances whose `info` says they serve `factord/rpc` now.
pub async fn gateways(z: &zenoh::Session) -> Vec<String> {
    infos(z)
        .await
        .into_iter()
        .filter(|i| i["rpc_gateway"] == true)
        .map(|i| i["instance"].as_str().unwrap_or_default().to_string())
        .collect()
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_default()
}
