//! The web view in a real browser: headless Chromium driven over WebDriver (chromedriver) against
//! a running server whose sessions are being fed, waiting for the trajectory and the live
//! convergence plot to render, with screenshots saved for people to look at.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::server::{client, create, g2o_batches, post, TestServer};
use serde_json::{json, Value};

const CHROMIUM: &str = "/usr/bin/chromium";
const CHROMEDRIVER: &str = "/usr/bin/chromedriver";

/// Debian's chromium and chromedriver, installed on first use when we may (root with apt).
fn browser() -> Result<(), String> {
    if Path::new(CHROMIUM).exists() && Path::new(CHROMEDRIVER).exists() {
        return Ok(());
    }
    let out = Command::new("apt-get")
        .args([
            "install",
            "-y",
            "--no-install-recommends",
            "chromium",
            "chromium-driver",
        ])
        .env("DEBIAN_FRONTEND", "noninteractive")
        .output()
        .map_err(|e| format!("apt-get: {e}"))?;
    if out.status.success() && Path::new(CHROMEDRIVER).exists() {
        Ok(())
    } else {
        Err(format!(
            "cannot install chromium and chromium-driver: {}",
            String::from_utf8_lossy(&out.stderr)
        ))
    }
}

/// A WebDriver session in headless Chromium; the driver is stopped on drop.
struct Browser {
    driver: Child,
    base: String,
    http: reqwest::Client,
}

impl Browser {
    async fn start(profile: &Path) -> Self {
        let port = common::server::free_port();
        let driver = Command::new(CHROMEDRIVER)
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("chromedriver starts");
        let http = reqwest::Client::new();
        let root = format!("http://127.0.0.1:{port}");
        // The flags keep Chromium off the network this machine does not have.
        let capabilities = json!({"capabilities": {"alwaysMatch": {"goog:chromeOptions": {
            "binary": CHROMIUM,
            "args": ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                     "--no-first-run", "--disable-background-networking",
                     "--disable-component-update", "--disable-sync",
                     "--window-size=1280,1600",
                     format!("--user-data-dir={}", profile.display())]}}}});
        let deadline = Instant::now() + Duration::from_secs(30);
        let session = loop {
            let reply = http
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
        Self {
            driver,
            base: format!("{root}/session/{session}"),
            http,
        }
    }

    async fn command(&self, method: reqwest::Method, path: &str, body: Option<Value>) -> Value {
        let mut request = self.http.request(method, format!("{}{path}", self.base));
        if let Some(body) = body {
            request = request.json(&body);
        }
        let v: Value = request.send().await.unwrap().json().await.unwrap();
        assert!(v["value"].get("error").is_none(), "WebDriver {path}: {v}");
        v["value"].clone()
    }

    async fn open(&self, url: &str) {
        self.command(reqwest::Method::POST, "/url", Some(json!({"url": url})))
            .await;
    }

    async fn script(&self, script: &str) -> Value {
        let body = json!({"script": script, "args": []});
        self.command(reqwest::Method::POST, "/execute/sync", Some(body))
            .await
    }

    /// Polls `condition` (a JS expression) until it is true; returns the page's test hooks.
    async fn wait_for(&self, condition: &str, what: &str) -> Value {
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
    async fn inked_pixels(&self, id: &str) -> u64 {
        let script = format!(
            "const c = document.getElementById('{id}'); const d = c.getContext('2d')\
             .getImageData(0, 0, c.width, c.height).data; let n = 0;\
             for (let i = 0; i < d.length; i += 4) {{ if (d[i] != d[0] || d[i+1] != d[1] || d[i+2] != d[2]) n++; }}\
             return n;"
        );
        self.script(&script).await.as_u64().unwrap()
    }

    async fn click(&self, css: &str) {
        let body = json!({"using": "css selector", "value": css});
        let element = self
            .command(reqwest::Method::POST, "/element", Some(body))
            .await;
        let id = element
            .as_object()
            .and_then(|o| o.values().next())
            .and_then(Value::as_str)
            .unwrap()
            .to_string();
        self.command(
            reqwest::Method::POST,
            &format!("/element/{id}/click"),
            Some(json!({})),
        )
        .await;
    }

    async fn screenshot(&self, path: &Path) {
        let png = self
            .command(reqwest::Method::GET, "/screenshot", None)
            .await;
        let bytes = base64_decode(png.as_str().unwrap());
        // A real PNG of the window.
        let decoder = png::Decoder::new(std::io::Cursor::new(&bytes));
        let info = decoder.read_info().unwrap().info().clone();
        assert!(
            info.width >= 1000 && info.height >= 800,
            "{}x{}",
            info.width,
            info.height
        );
        std::fs::write(path, bytes).unwrap();
        println!("screenshot: {}", path.display());
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.driver.kill();
        let _ = self.driver.wait();
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

fn screenshot_dir() -> PathBuf {
    let dir = std::env::var_os("FACTORD_SCREENSHOT_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| std::env::temp_dir().join("factord-web-view"));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[tokio::test(flavor = "multi_thread")]
async fn web_view_draws_sessions_being_fed() {
    if let Err(reason) = browser() {
        common::skip_or_fail::<()>(&format!("no headless Chromium: {reason}"));
        return;
    }
    let s = TestServer::start(&[]);
    let c = client();
    let shots = screenshot_dir();

    // A 2D session fed pose by pose while the browser watches (intel when the data is there).
    let text = match common::data_file("2d/converted/intel_lsslam.g2o") {
        Some(path) => std::fs::read_to_string(path).unwrap(),
        None => common::synthetic_manhattan(400, 3),
    };
    let batches = g2o_batches(&text);
    let total = batches.len();
    create(&c, &s, &json!({"session": "robot", "kind": "pose_graph_2d", "options": {"method": "levenberg_marquardt"}})).await;
    // A 3D session, loaded at once.
    create(
        &c,
        &s,
        &json!({"session": "helix", "kind": "pose_graph_3d"}),
    )
    .await;
    for b in g2o_batches(&common::synthetic_helix_3d(200, 2)) {
        let (status, v) = post(&c, &s.url("/v1/sessions/helix/batches"), &b).await;
        assert_eq!(status, 200, "{v}");
    }

    let profile = common::temp_dir("chromium-profile");
    let browser = Browser::start(&profile).await;
    let page = s.url("/sessions/robot");
    browser.open(&page).await;
    browser
        .wait_for(
            "document.body.dataset.eventsConnected === 'true'",
            "the event stream",
        )
        .await;

    // Feed the first half while the page is open: the plot fills from the live stream.
    let feeder = {
        let (c, url) = (c.clone(), s.url("/v1/sessions/robot/batches"));
        tokio::spawn(async move {
            for b in batches {
                let (status, v) = post(&c, &url, &b).await;
                assert_eq!(status, 200, "{v}");
                tokio::time::sleep(Duration::from_millis(2)).await;
            }
        })
    };
    let hooks = browser
        .wait_for(
            "Number(document.body.dataset.plotIterations) >= 5 && Number(document.body.dataset.trajectoryPoints) >= 50",
            "the convergence plot and trajectory while feeding",
        )
        .await;
    println!("while feeding: {hooks}");
    browser.screenshot(&shots.join("session-feeding.png")).await;
    feeder.await.unwrap();
    let hooks = browser
        .wait_for(
            &format!("Number(document.body.dataset.trajectoryPoints) === {total}"),
            "every pose on the trajectory",
        )
        .await;
    assert!(
        hooks["plotIterations"]
            .as_str()
            .unwrap()
            .parse::<u64>()
            .unwrap()
            >= 5,
        "{hooks}"
    );
    assert!(browser.inked_pixels("trajectory").await > 2_000);
    assert!(browser.inked_pixels("convergence").await > 500);
    // Loop closures on demand add ink.
    let before = browser.inked_pixels("trajectory").await;
    browser.click("#show-loops").await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let with_loops = browser.inked_pixels("trajectory").await;
    assert!(
        with_loops > before,
        "loop closures drew nothing: {before} → {with_loops}"
    );
    browser.screenshot(&shots.join("session-loops.png")).await;

    // The 3D session, from the front and in orbit.
    browser.open(&s.url("/sessions/helix")).await;
    browser
        .wait_for(
            "Number(document.body.dataset.trajectoryPoints) === 200",
            "the 3D trajectory",
        )
        .await;
    browser
        .script("const p = document.getElementById('projection'); p.value = 'front'; p.dispatchEvent(new Event('change')); return p.value;")
        .await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert!(browser.inked_pixels("trajectory").await > 1_000);
    browser
        .screenshot(&shots.join("session-3d-front.png"))
        .await;

    // A bundle-adjustment session's point cloud and camera centres (variables only: drawing
    // needs no observations).
    create(
        &c,
        &s,
        &json!({"session": "cloud", "kind": "bundle_adjustment"}),
    )
    .await;
    let mut variables: Vec<Value> = (0..8)
        .map(|i| {
            json!({"key": i, "kind": "snavely_camera",
            "value": [0.0, 0.3 * i as f64, 0.0, i as f64 * 0.5, 0.0, 4.0, 500.0, 0.0, 0.0]})
        })
        .collect();
    for j in 0..3000u64 {
        let (a, b) = (j as f64 * 0.618_034, j as f64 * 0.001);
        variables.push(json!({"key": 100 + j, "kind": "point3",
            "value": [3.0 * a.cos() * (1.0 + b), 3.0 * a.sin(), 2.0 * (b - 1.5)]}));
    }
    let (status, v) = post(
        &c,
        &s.url("/v1/sessions/cloud/batches"),
        &json!({"variables": variables}),
    )
    .await;
    assert_eq!(status, 200, "{v}");
    browser.open(&s.url("/sessions/cloud")).await;
    let hooks = browser
        .wait_for(
            "Number(document.body.dataset.pointsDrawn) === 3000 && Number(document.body.dataset.trajectoryPoints) === 8",
            "the point cloud and camera centres",
        )
        .await;
    println!("bundle adjustment: {hooks}");
    assert!(browser.inked_pixels("trajectory").await > 2_000);
    browser
        .screenshot(&shots.join("session-ba-points.png"))
        .await;

    // 2D landmarks (point2) drawn with the trajectory of a pose graph session.
    create(
        &c,
        &s,
        &json!({"session": "trees", "kind": "pose_graph_2d"}),
    )
    .await;
    let mut variables: Vec<Value> = (0..10)
        .map(|i| json!({"key": i, "kind": "se2", "value": [i as f64, 0.0, 0.0]}))
        .collect();
    for l in 0..5u64 {
        variables.push(json!({"key": 100 + l, "kind": "point2", "value": [2.0 * l as f64, 3.0]}));
    }
    let (status, v) = post(
        &c,
        &s.url("/v1/sessions/trees/batches"),
        &json!({"variables": variables}),
    )
    .await;
    assert_eq!(status, 200, "{v}");
    browser.open(&s.url("/sessions/trees")).await;
    browser
        .wait_for(
            "Number(document.body.dataset.pointsDrawn) === 5 && Number(document.body.dataset.trajectoryPoints) === 10",
            "the landmarks and the poses",
        )
        .await;

    // The list of sessions.
    browser.open(&s.url("/")).await;
    let hooks = browser
        .wait_for(
            "Number(document.body.dataset.sessionsListed) === 4",
            "the session list",
        )
        .await;
    println!("index: {hooks}");
    let listed = browser.script("return document.body.innerText;").await;
    let listed = listed.as_str().unwrap();
    assert!(
        listed.contains("robot") && listed.contains("helix") && listed.contains("trees"),
        "{listed}"
    );
    browser.screenshot(&shots.join("index.png")).await;

    // An unknown session is a 404 page, not an empty view.
    let missing = c.get(s.url("/sessions/nobody")).send().await.unwrap();
    assert_eq!(missing.status(), 404);
    s.assert_no_panic();
}
