//! Headless Chromium driven over WebDriver (chromedriver), and nothing of it left behind.
//!
//! chromedriver is started as the leader of its own process group, and Chromium (started by
//! chromedriver) inherits it. [`Browser`]'s drop ends the whole group (SIGTERM, then SIGKILL),
//! and then any process still naming our unique profile directory on its command line (in case
//! one left the group), whether the test passed, failed or panicked: unwinding drops the guard.
//! Only processes of our group or our profile are ever signalled, never "all chromiums": other
//! people's tests on this machine run browsers too. [`survivors`] lists what remains of ours.

use std::os::unix::process::CommandExt as _;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::{json, Value};

pub const CHROMIUM: &str = "/usr/bin/chromium";
pub const CHROMEDRIVER: &str = "/usr/bin/chromedriver";

/// Debian's chromium and chromedriver, installed on first use when we may (root with apt), by
/// one test at a time (apt takes one install at a time; see `environments::locked`), after
/// `apt-get update` when the package lists of a fresh machine do not know them.
pub fn install() -> Result<(), String> {
    let present = || Path::new(CHROMIUM).exists() && Path::new(CHROMEDRIVER).exists();
    if present() {
        return Ok(());
    }
    let cache = super::environments::cache_dir()?;
    super::environments::locked(&cache, "browser", || {
        if present() {
            return Ok(());
        }
        let mut failure = apt_install();
        if failure.is_some() {
            apt(&["update"]).map_err(|e| format!("apt-get update: {e}"))?;
            failure = apt_install();
        }
        match failure {
            None if present() => Ok(()),
            None => Err("apt-get installed chromium, but not where expected".into()),
            Some(why) => Err(format!(
                "cannot install chromium and chromium-driver: {why}"
            )),
        }
    })?
}

/// Installs chromium and chromium-driver; `Some(why)` when apt-get failed.
fn apt_install() -> Option<String> {
    let packages = [
        "install",
        "-y",
        "--no-install-recommends",
        "chromium",
        "chromium-driver",
    ];
    apt(&packages).err()
}

fn apt(args: &[&str]) -> Result<(), String> {
    let out = Command::new("apt-get")
        .args(args)
        .env("DEBIAN_FRONTEND", "noninteractive")
        .output()
        .map_err(|e| format!("apt-get: {e}"))?;
    match out.status.success() {
        true => Ok(()),
        false => Err(String::from_utf8_lossy(&out.stderr).into_owned()),
    }
}

/// What identifies our browser's processes: the process group chromedriver leads, and the
/// profile directory made for this browser alone.
#[derive(Clone, Debug)]
pub struct Identity {
    pub group: i32,
    pub profile: PathBuf,
}

/// A live process: pid, state letter, process group, command line.
#[derive(Debug)]
pub struct Process {
    pub pid: i32,
    pub state: char,
    pub group: i32,
    pub cmdline: String,
}

/// Every process on the machine (from `/proc`), zombies included.
pub fn processes() -> Vec<Process> {
    let mut out = Vec::new();
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return out;
    };
    for entry in entries.flatten() {
        let Some(pid) = entry
            .file_name()
            .to_str()
            .and_then(|n| n.parse::<i32>().ok())
        else {
            continue;
        };
        let Ok(stat) = std::fs::read_to_string(entry.path().join("stat")) else {
            continue;
        };
        // `pid (comm) state ppid pgrp …`; comm may hold spaces and parentheses.
        let Some(after) = stat.rfind(')').map(|i| &stat[i + 1..]) else {
            continue;
        };
        let fields: Vec<&str> = after.split_whitespace().collect();
        let (Some(state), Some(group)) = (
            fields.first().and_then(|s| s.chars().next()),
            fields.get(2).and_then(|g| g.parse().ok()),
        ) else {
            continue;
        };
        let cmdline = std::fs::read(entry.path().join("cmdline"))
            .map(|b| String::from_utf8_lossy(&b).replace('\0', " "))
            .unwrap_or_default();
        out.push(Process {
            pid,
            state,
            group,
            cmdline,
        });
    }
    out
}

/// Our browser's processes still alive (zombies are dead: they hold nothing but a pid).
pub fn survivors(who: &Identity) -> Vec<Process> {
    let profile = who.profile.display().to_string();
    processes()
        .into_iter()
        .filter(|p| p.state != 'Z')
        .filter(|p| p.group == who.group || p.cmdline.contains(&profile))
        .collect()
}

/// Ends every process of `who`: the group politely, then firmly, then stragglers by profile.
fn end_all(who: &Identity) {
    // SAFETY: kill(2) with a negative pid signals exactly our group (chromedriver's pid).
    unsafe { libc::kill(-who.group, libc::SIGTERM) };
    let deadline = Instant::now() + Duration::from_secs(3);
    while !survivors(who).is_empty() && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(50));
    }
    for _ in 0..3 {
        let left = survivors(who);
        if left.is_empty() {
            return;
        }
        // SAFETY: as above; then each process still naming our profile, by its own pid.
        unsafe { libc::kill(-who.group, libc::SIGKILL) };
        for p in left {
            unsafe { libc::kill(p.pid, libc::SIGKILL) };
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// A WebDriver session in headless Chromium. Dropping it ends every process it started.
pub struct Browser {
    driver: Child,
    who: Identity,
    base: String,
    http: reqwest::Client,
}

impl Browser {
    /// chromedriver and Chromium with a fresh profile directory (removed on drop).
    pub async fn start(name: &str) -> Self {
        Self::start_sized(name, (1280, 1600)).await
    }

    /// [`Browser::start`] with a window of `size` (width, height) pixels.
    pub async fn start_sized(name: &str, size: (u32, u32)) -> Self {
        let profile = super::temp_dir(&format!("chromium-profile-{name}"));
        let port = super::server::free_port();
        let driver = Command::new(CHROMEDRIVER)
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            // Its own process group, which Chromium and its helpers inherit.
            .process_group(0)
            .spawn()
            .expect("chromedriver starts");
        let who = Identity {
            group: driver.id() as i32,
            profile,
        };
        // The guard exists from here on: a panic below still ends chromedriver.
        let mut browser = Self {
            driver,
            who,
            base: String::new(),
            http: reqwest::Client::new(),
        };
        let root = format!("http://127.0.0.1:{port}");
        // The flags keep Chromium off the network this machine does not have.
        let capabilities = json!({"capabilities": {"alwaysMatch": {"goog:chromeOptions": {
            "binary": CHROMIUM,
            "args": ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                     "--no-first-run", "--disable-background-networking",
                     "--disable-component-update", "--disable-sync",
                     format!("--window-size={},{}", size.0, size.1),
                     format!("--user-data-dir={}", browser.who.profile.display())]}}}});
        let deadline = Instant::now() + Duration::from_secs(30);
        let session = loop {
            let reply = browser
                .http
                .post(format!("{root}/session"))
                .json(&capabilities)
                .send()
                .await;
            if let Ok(reply) = reply {
                let v: Value = reply.json().await.unwrap();
                match v["value"]["sessionId"].as_str() {
                    Some(id) => break id.to_string(),
                    None => panic!("chromedriver refused the session: {v}"),
                }
            }
            assert!(Instant::now() < deadline, "chromedriver did not start");
            tokio::time::sleep(Duration::from_millis(100)).await;
        };
        browser.base = format!("{root}/session/{session}");
        browser
    }

    pub fn identity(&self) -> Identity {
        self.who.clone()
    }

    pub async fn command(&self, method: reqwest::Method, path: &str, body: Option<Value>) -> Value {
        let mut request = self.http.request(method, format!("{}{path}", self.base));
        if let Some(body) = body {
            request = request.json(&body);
        }
        let v: Value = request.send().await.unwrap().json().await.unwrap();
        assert!(v["value"].get("error").is_none(), "WebDriver {path}: {v}");
        v["value"].clone()
    }

    pub async fn open(&self, url: &str) {
        self.command(reqwest::Method::POST, "/url", Some(json!({"url": url})))
            .await;
    }

    pub async fn script(&self, script: &str) -> Value {
        let body = json!({"script": script, "args": []});
        self.command(reqwest::Method::POST, "/execute/sync", Some(body))
            .await
    }

    /// Sets the value of control `id` and fires `event` on it (`change` for a select, `input`
    /// for a text field), as a user's edit does.
    pub async fn set_control(&self, id: &str, value: &str, event: &str) {
        self.script(&format!(
            "const e = document.getElementById('{id}'); e.value = '{value}'; \
             e.dispatchEvent(new Event('{event}')); return e.value;"
        ))
        .await;
    }

    /// Polls `condition` (a JS expression) until it is true; returns the page's test hooks.
    pub async fn wait_for(&self, condition: &str, what: &str) -> Value {
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            let ok = self.script(&format!("return Boolean({condition});")).await;
            if ok == json!(true) {
                return self
                    .script("return Object.assign({}, document.body.dataset);")
                    .await;
            }
            let hooks = self
                .script("return Object.assign({}, document.body.dataset);")
                .await;
            assert!(
                Instant::now() < deadline,
                "timed out waiting for {what}: {hooks}"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    /// Pixels of canvas `id` that differ from its top-left (background) pixel.
    pub async fn inked_pixels(&self, id: &str) -> u64 {
        let script = format!(
            "const c = document.getElementById('{id}'); const d = c.getContext('2d')\
             .getImageData(0, 0, c.width, c.height).data; let n = 0;\
             for (let i = 0; i < d.length; i += 4) {{ if (d[i] != d[0] || d[i+1] != d[1] || d[i+2] != d[2]) n++; }}\
             return n;"
        );
        self.script(&script).await.as_u64().unwrap()
    }

    /// The WebDriver id of the first element matching `css`.
    pub async fn element(&self, css: &str) -> String {
        let body = json!({"using": "css selector", "value": css});
        let element = self
            .command(reqwest::Method::POST, "/element", Some(body))
            .await;
        element
            .as_object()
            .and_then(|o| o.values().next())
            .and_then(Value::as_str)
            .unwrap()
            .to_string()
    }

    pub async fn click(&self, css: &str) {
        let id = self.element(css).await;
        self.command(
            reqwest::Method::POST,
            &format!("/element/{id}/click"),
            Some(json!({})),
        )
        .await;
    }

    /// Types `text` into the element matching `css`, as keystrokes.
    pub async fn type_into(&self, css: &str, text: &str) {
        let id = self.element(css).await;
        self.command(
            reqwest::Method::POST,
            &format!("/element/{id}/value"),
            Some(json!({"text": text})),
        )
        .await;
    }

    /// The window as PNG bytes, checked to be a real PNG of at least `min` pixels each way.
    pub async fn screenshot_png(&self, min: (u32, u32)) -> Vec<u8> {
        let png = self
            .command(reqwest::Method::GET, "/screenshot", None)
            .await;
        let bytes = base64_decode(png.as_str().unwrap());
        let decoder = png::Decoder::new(std::io::Cursor::new(&bytes));
        let info = decoder.read_info().unwrap().info().clone();
        assert!(
            info.width >= min.0 && info.height >= min.1,
            "{}x{}",
            info.width,
            info.height
        );
        bytes
    }

    pub async fn screenshot(&self, path: &Path) {
        let bytes = self.screenshot_png((1000, 800)).await;
        std::fs::write(path, bytes).unwrap();
        println!("screenshot: {}", path.display());
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        end_all(&self.who);
        let _ = self.driver.kill();
        let _ = self.driver.wait();
        let _ = std::fs::remove_dir_all(&self.who.profile);
    }
}

/// Standard base64 (WebDriver screenshots), without a crate for twenty lines.
fn base64_decode(text: &str) -> Vec<u8> {
    let value = |c: u8| -> u32 {
        match c {
            b'A'..=b'Z' => (c - b'A') as u32,
            b'a'..=b'z' => (c - b'a' + 26) as u32,
            b'0'..=b'9' => (c - b'0' + 52) as u32,
            b'+' => 62,
            b'/' => 63,
            _ => panic!("not base64: {c}"),
        }
    };
    let clean: Vec<u8> = text
        .bytes()
        .filter(|c| !c.is_ascii_whitespace() && *c != b'=')
        .collect();
    let mut out = Vec::with_capacity(clean.len() * 3 / 4);
    for chunk in clean.chunks(4) {
        let mut acc = 0u32;
        for (i, &c) in chunk.iter().enumerate() {
            acc |= value(c) << (18 - 6 * i);
        }
        out.extend_from_slice(&acc.to_be_bytes()[1..chunk.len()]);
    }
    out
}
