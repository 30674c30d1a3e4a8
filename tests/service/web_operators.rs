//! The web view for operators, in headless Chromium against a server with tokens: the login form
//! (a token exchanged for an HttpOnly cookie; the event stream then connects), the health panel,
//! the session's history after a reload (timeline, event log and convergence refilled from the
//! server, rejected inputs, last_error), covariance ellipses of selected poses, edges coloured by
//! χ² against a threshold, and the export links. Screenshots go to `FACTORD_SCREENSHOT_DIR`
//! (`docs/screenshots/` holds the committed ones).

use crate::common;

use std::path::PathBuf;
use std::time::{Duration, Instant};

use common::browser::{self, survivors, Browser};
use common::server::{create, g2o_batches, post, TestServer};
use serde_json::{json, Value};

const TOKEN: &str = "operator-0123456789abcdef";

fn screenshot_dir() -> PathBuf {
    let dir = std::env::var_os("FACTORD_SCREENSHOT_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| std::env::temp_dir().join("factord-web-view"));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A client that sends the operator's bearer token.
fn authorised() -> reqwest::Client {
    let mut headers = reqwest::header::HeaderMap::new();
    headers.insert(
        reqwest::header::AUTHORIZATION,
        format!("Bearer {TOKEN}").parse().unwrap(),
    );
    reqwest::Client::builder()
        .default_headers(headers)
        .build()
        .unwrap()
}

/// Waits until the session's estimate reflects every batch and no solve runs.
async fn settled(c: &reqwest::Client, url: &str) -> Value {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let stats: Value = c.get(url).send().await.unwrap().json().await.unwrap();
        if stats["solved_sequence"] == stats["sequence"] && stats["solving"] == false {
            return stats;
        }
        assert!(Instant::now() < deadline, "never settled: {stats}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn operators_log_in_and_read_history_ellipses_and_outliers() {
    if let Err(reason) = browser::install() {
        common::skip_or_fail::<()>(&format!("no headless Chromium: {reason}"));
        return;
    }
    let dir = common::temp_dir("web-operators");
    let tokens = dir.join("tokens");
    std::fs::write(&tokens, format!("operator {TOKEN}\n")).unwrap();
    let tokens = tokens.display().to_string();
    let s = TestServer::start_at(
        &dir.join("state"),
        &["--no-zenoh", "--tokens-file", &tokens],
        &[],
    );
    let c = authorised();
    let shots = screenshot_dir();

    // A planar session fed in batches (each solved), one rejected batch, one loop closure
    // corrupted into an outlier.
    create(
        &c,
        &s,
        &json!({"session": "robot", "kind": "pose_graph_2d"}),
    )
    .await;
    let text = common::synthetic_manhattan(300, 7);
    let batches = g2o_batches(&text);
    let batch_url = s.url("/v1/sessions/robot/batches");
    let stats_url = s.url("/v1/sessions/robot");
    for (i, b) in batches.iter().enumerate() {
        let (status, v) = post(&c, &batch_url, b).await;
        assert_eq!(status, 200, "{v}");
        if i % 25 == 0 {
            settled(&c, &stats_url).await;
        }
    }
    let bad = json!({"variables": [{"key": 9999, "kind": "nonsense", "value": [0.0]}]});
    let (status, v) = post(&c, &batch_url, &bad).await;
    assert_eq!(status, 400, "{v}");
    let outlier = json!({"factors": [{"type": "between_se2", "keys": [0, 150],
        "measurement": [40.0, -25.0, 2.0], "information": [1, 0, 0, 1, 0, 1]}]});
    let (status, v) = post(&c, &batch_url, &outlier).await;
    assert_eq!(status, 200, "{v}");
    let stats = settled(&c, &stats_url).await;
    println!("solves: {}", stats["solves"]);

    // The history the page will read: a point per solve with its latency, the log bounded (300
    // acks and as many summaries make more than 200 events), the refused rpc batch kept.
    let h: Value = c
        .get(s.url("/v1/sessions/robot/history"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let timeline = h["timeline"].as_array().unwrap();
    // (A solve that stops at its iteration limit is followed by another: more may come.)
    assert!(timeline.len() >= 100, "{} points: {stats}", timeline.len());
    let latency = |p: &Value| p["latency_seconds"].as_f64();
    assert!(timeline.iter().all(|p| latency(p).is_none_or(|l| l >= 0.0)));
    assert!(
        timeline
            .iter()
            .any(|p| latency(p).is_some_and(|l| l >= p["solve_seconds"].as_f64().unwrap())),
        "a batch waits at least as long as the solve that reflects it"
    );
    assert_eq!(h["events"].as_array().unwrap().len(), 200);
    assert!(h["dropped"].as_u64().unwrap() > 0);
    assert_eq!(
        h["rejected"].as_array().unwrap().len(),
        1,
        "{}",
        h["rejected"]
    );
    assert_eq!(
        h["rejected"][0]["data"]["error"]["field"],
        "variables[0].kind"
    );
    assert_eq!(h["last_error"], Value::Null);

    // Tall enough for the timeline in the screenshot.
    let browser = Browser::start_sized("operators", (1280, 1900)).await;
    let ours = browser.identity();

    // Without the cookie the index asks for a token; the form logs in and the page reloads.
    browser.open(&s.url("/")).await;
    browser
        .wait_for(
            "document.body.dataset.loginShown === 'true'",
            "the login form",
        )
        .await;
    // Until the login the form is all there is: no red 401 line, no "loading…" table, no
    // health panel, no "log out" (issue 56), also after the index's retry (every 2 s).
    tokio::time::sleep(Duration::from_millis(2500)).await;
    let before_login = browser
        .script("const shown = (css) => [...document.querySelectorAll(css)].some((e) => e.offsetParent !== null); \
                 return {status: document.getElementById('status').innerText, table: shown('table.sessions'), \
                 health: shown('#health'), login: shown('#login-form'), logout: shown('#logout'), \
                 text: document.body.innerText};")
        .await;
    assert_eq!(before_login["login"], true, "{before_login}");
    for hidden in ["table", "health", "logout"] {
        assert_eq!(before_login[hidden], false, "{hidden}: {before_login}");
    }
    let text = before_login["text"].as_str().unwrap();
    assert!(
        !text.contains("401") && !text.contains("loading") && !text.contains("retrying"),
        "{text}"
    );
    browser.type_into("#login-token", TOKEN).await;
    browser.click("#login-submit").await;
    tokio::time::sleep(Duration::from_millis(800)).await;
    let hooks = browser
        .wait_for(
            "Number(document.body.dataset.sessionsListed) === 1 && document.body.dataset.healthStatus === 'ok'",
            "the session list and health after login",
        )
        .await;
    println!("index after login: {hooks}");
    let logout = browser
        .script("return document.getElementById('logout').hidden;")
        .await;
    assert_eq!(logout, json!(false), "log out is offered once logged in");
    // The cookie is HttpOnly: the page's scripts never see the token.
    let cookies = browser.script("return document.cookie;").await;
    assert!(
        !cookies.as_str().unwrap().contains("factord_session"),
        "{cookies}"
    );
    browser.screenshot(&shots.join("operator-index.png")).await;

    // The session page: the stream connects with the cookie; the history fills the timeline,
    // the event log and the rejected inputs.
    let page = s.url("/sessions/robot");
    browser.open(&page).await;
    let loaded = "document.body.dataset.eventsConnected === 'true' && document.body.dataset.historyLoaded === 'true' \
                  && Number(document.body.dataset.timelinePoints) >= 5 && Number(document.body.dataset.logEntries) >= 10 \
                  && Number(document.body.dataset.rejected) === 1 && Number(document.body.dataset.plotIterations) >= 2";
    let first = browser.wait_for(loaded, "the session's history").await;
    println!("session: {first}");
    // A reload without anything new: the same history, from the server.
    browser.open(&page).await;
    let again = browser.wait_for(loaded, "the history after a reload").await;
    assert_eq!(
        first["timelinePoints"], again["timelinePoints"],
        "{first} vs {again}"
    );
    let rejected = browser
        .script("return document.getElementById('rejected').innerText;")
        .await;
    assert!(
        rejected.as_str().unwrap().contains("variables[0].kind"),
        "{rejected}"
    );
    let log = browser
        .script("return document.getElementById('log').innerText;")
        .await;
    assert!(
        log.as_str().unwrap().contains("accepted")
            && log.as_str().unwrap().contains("incremental update"),
        "{log}"
    );
    // Colour by meaning: green only for a converged solve; an incremental update is neutral
    // and never reads as a solve that failed to converge.
    let entries = browser
        .script("return [...document.querySelectorAll('#log li')].map((li) => [li.className, li.innerText]);")
        .await;
    let entries = entries.as_array().unwrap();
    assert!(entries.iter().any(|e| e[0] == "update"), "{entries:?}");
    for entry in entries {
        let (class, text) = (entry[0].as_str().unwrap(), entry[1].as_str().unwrap());
        if class == "summary" {
            assert!(
                !text.contains("not converged"),
                "green but not converged: {text}"
            );
        }
        if class == "update" {
            assert!(
                text.contains("incremental update") && !text.contains("iterations"),
                "{text}"
            );
        }
    }

    // Export links point at the estimate in each format.
    let hrefs = browser
        .script("return ['g2o','tum','ply'].map((f) => document.getElementById('export-' + f).getAttribute('href'));")
        .await;
    assert_eq!(
        hrefs,
        json!([
            "/v1/sessions/robot/estimate?format=g2o",
            "/v1/sessions/robot/estimate?format=tum",
            "/v1/sessions/robot/estimate?format=ply"
        ])
    );
    // …and they download with the login cookie alone (a synchronous XHR, as a click would).
    let tum = browser
        .script("const x = new XMLHttpRequest(); x.open('GET', document.getElementById('export-tum').getAttribute('href'), false); x.send(); return [x.status, x.responseText];")
        .await;
    assert_eq!(tum[0], 200, "{tum}");
    assert!(
        tum[1]
            .as_str()
            .unwrap()
            .starts_with("# timestamp tx ty tz qx qy qz qw\n"),
        "{tum}"
    );

    // Edges by χ²: the corrupted loop closure stands out at the default threshold; nothing
    // is above an absurd one.
    browser.click("#show-residuals").await;
    let hooks = browser
        .wait_for(
            "Number(document.body.dataset.edgesOverThreshold) >= 1",
            "the outlier edge in red",
        )
        .await;
    let over = hooks["edgesOverThreshold"]
        .as_str()
        .unwrap()
        .parse::<u64>()
        .unwrap();
    let edges = browser
        .script("return document.getElementById('graph-info').textContent;")
        .await;
    // The outlier drags its neighbours a little; most edges stay below.
    assert!(over < 60, "{over} edges above 7.81: {edges}");
    browser
        .set_control("residual-threshold", "1e300", "input")
        .await;
    browser
        .wait_for(
            "document.body.dataset.edgesOverThreshold === '0'",
            "no edge above an absurd threshold",
        )
        .await;
    browser
        .set_control("residual-threshold", "7.81", "input")
        .await;

    // Covariance ellipses for a sample of poses, from the marginals route.
    let before = browser.inked_pixels("trajectory").await;
    browser.click("#ellipse-sample").await;
    let hooks = browser
        .wait_for(
            "Number(document.body.dataset.ellipsesDrawn) >= 5",
            "the covariance ellipses",
        )
        .await;
    println!("ellipses: {hooks}");
    tokio::time::sleep(Duration::from_millis(300)).await;
    let with_ellipses = browser.inked_pixels("trajectory").await;
    assert!(
        with_ellipses > before,
        "ellipses drew nothing: {before} → {with_ellipses}"
    );
    assert!(browser.inked_pixels("timeline").await > 500);
    browser
        .screenshot(&shots.join("operator-session.png"))
        .await;

    // A 3D session: ellipses of the world position covariance (an se3's tangent is the body's),
    // projected on the view, here from the front.
    create(
        &c,
        &s,
        &json!({"session": "helix", "kind": "pose_graph_3d"}),
    )
    .await;
    for b in g2o_batches(&common::synthetic_helix_3d(120, 2)) {
        let (status, v) = post(&c, &s.url("/v1/sessions/helix/batches"), &b).await;
        assert_eq!(status, 200, "{v}");
    }
    settled(&c, &s.url("/v1/sessions/helix")).await;
    browser.open(&s.url("/sessions/helix")).await;
    browser
        .wait_for(
            "Number(document.body.dataset.trajectoryPoints) === 120",
            "the 3D trajectory",
        )
        .await;
    browser.set_control("projection", "front", "change").await;
    browser.set_control("ellipse-scale", "10", "change").await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let before = browser.inked_pixels("trajectory").await;
    browser.click("#ellipse-sample").await;
    browser
        .wait_for(
            "Number(document.body.dataset.ellipsesDrawn) >= 5",
            "the 3D covariance ellipses",
        )
        .await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let with_ellipses = browser.inked_pixels("trajectory").await;
    assert!(
        with_ellipses > before,
        "3D ellipses drew nothing: {before} → {with_ellipses}"
    );
    browser
        .screenshot(&shots.join("operator-3d-ellipses.png"))
        .await;

    drop(browser);
    let left = survivors(&ours);
    assert!(
        left.is_empty(),
        "browser processes outlived the test: {left:?}"
    );
    s.assert_no_panic();
}
