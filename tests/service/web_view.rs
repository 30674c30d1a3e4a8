//! The web view in a real browser: headless Chromium driven over WebDriver (chromedriver) against
//! a running server whose sessions are being fed, waiting for the trajectory and the live
//! convergence plot to render, with screenshots saved for people to look at.

use crate::common;

use std::path::PathBuf;
use std::time::Duration;

use common::browser::{self, survivors, Browser};
use common::server::{client, create, g2o_batches, post, TestServer};
use serde_json::{json, Value};

fn screenshot_dir() -> PathBuf {
    let dir = std::env::var_os("FACTORD_SCREENSHOT_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| std::env::temp_dir().join("factord-web-view"));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[tokio::test(flavor = "multi_thread")]
async fn web_view_draws_sessions_being_fed() {
    if let Err(reason) = browser::install() {
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

    let browser = Browser::start("draws").await;
    let ours = browser.identity();
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
    // The convergence plot's x axis is solves (issue 56): one colour band and tick per solve,
    // labelled with the solve's number.
    let solves: u64 = hooks["plotSolves"].as_str().unwrap().parse().unwrap();
    let labels: u64 = hooks["plotSolveLabels"].as_str().unwrap().parse().unwrap();
    assert!(solves >= 2 && (1..=solves).contains(&labels), "{hooks}");
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
    browser.set_control("projection", "front", "change").await;
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
    // No tokens on this server: nothing to log out of (issue 56).
    let logout = browser
        .script("return document.getElementById('logout').hidden;")
        .await;
    assert_eq!(
        logout,
        json!(true),
        "log out shown on a server without tokens"
    );

    // The API page renders the descriptions' Markdown code spans, not their backticks.
    browser.open(&s.url("/v1/docs")).await;
    let docs = browser
        .wait_for(
            "document.querySelectorAll('#schemas .schema').length > 10",
            "the API page",
        )
        .await;
    println!("docs: {docs}");
    let rendered = browser
        .script("return [document.querySelector('main').innerText, document.querySelectorAll('#operations p code, #operations td code, #schemas p code, #schemas td span code').length];")
        .await;
    let text = rendered[0].as_str().unwrap();
    assert!(
        !text.contains('`'),
        "raw backticks on /v1/docs: {}",
        text.lines().find(|l| l.contains('`')).unwrap_or("")
    );
    assert!(
        rendered[1].as_u64().unwrap() >= 20,
        "code spans: {rendered}"
    );

    // An unknown session is a 404 page, not an empty view.
    let missing = c.get(s.url("/sessions/nobody")).send().await.unwrap();
    assert_eq!(missing.status(), 404);
    s.assert_no_panic();
    drop(browser);
    let left = survivors(&ours);
    assert!(
        left.is_empty(),
        "browser processes outlived the test: {left:?}"
    );
}

/// A failing test leaves no browser behind: the guard ends chromedriver's process group (and
/// anything naming our profile) while the panic unwinds. Only our own processes are looked at.
#[tokio::test(flavor = "multi_thread")]
async fn no_browser_process_outlives_a_panicking_test() {
    if let Err(reason) = browser::install() {
        common::skip_or_fail::<()>(&format!("no headless Chromium: {reason}"));
        return;
    }
    let (tx, rx) = tokio::sync::oneshot::channel();
    let failing = tokio::spawn(async move {
        let browser = Browser::start("panics").await;
        browser
            .open("data:text/html,<title>about to fail</title>")
            .await;
        let ours = browser.identity();
        let running = survivors(&ours);
        tx.send((ours, running.len())).unwrap();
        panic!("this test fails on purpose, with the browser open");
    });
    let outcome = failing.await;
    assert!(outcome.as_ref().is_err_and(|e| e.is_panic()), "{outcome:?}");
    let (ours, running) = rx.await.unwrap();
    // Chromium and its helpers, and chromedriver, were there while the test ran.
    assert!(
        running >= 3,
        "only {running} browser processes seen running"
    );
    let left = survivors(&ours);
    assert!(
        left.is_empty(),
        "browser processes outlived the panic: {left:?}"
    );
    assert!(
        !ours.profile.exists(),
        "the profile directory was left behind"
    );
}
