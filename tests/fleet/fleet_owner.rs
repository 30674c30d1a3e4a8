//! Which instance of a fleet owns a session, over HTTP and in the web view (issue 56: a user had
//! to ask zenoh's `@fleet/<id>/info`): the creation answer, `GET /v1/sessions/<s>` and the merged
//! list name the owner whichever instance is asked, the session page's header shows it, and
//! after a kill -9 of an owner its sessions name their adopter.

use crate::common;

use std::time::{Duration, Instant};

use common::browser::{self, survivors, Browser};
use common::fleet::Fleet;
use common::server::zenoh_peer;
use serde_json::{json, Value};

/// GET `url` until it answers 200 with `ready(answer)` (a session moving answers 503 meanwhile).
async fn get_until(url: &str, ready: impl Fn(&Value) -> bool) -> Value {
    let c = reqwest::Client::builder()
        .timeout(Duration::from_secs(10))
        .build()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        if let Ok(answer) = c.get(url).send().await {
            if answer.status() == 200 {
                let v: Value = answer.json().await.unwrap();
                if ready(&v) {
                    return v;
                }
                assert!(Instant::now() < deadline, "{url}: {v}");
            }
        }
        assert!(Instant::now() < deadline, "{url}: not answered");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn every_answer_about_a_session_names_its_owning_instance() {
    let mut fleet = Fleet::start(3, &[]);
    let z = zenoh_peer(&fleet.instance(0).zenoh).await;
    fleet.wait_settled(&z).await;
    let c = reqwest::Client::new();
    let sessions: Vec<String> = (0..6).map(|i| format!("robot-{i}")).collect();
    for (k, name) in sessions.iter().enumerate() {
        let owner = fleet.id(fleet.owner(name)).to_string();
        let answer = c
            .post(fleet.instance(k % 3).url("/v1/sessions"))
            .json(&json!({"session": name, "kind": "pose_graph_2d"}))
            .send()
            .await
            .unwrap();
        assert_eq!(answer.status(), 201);
        let created: Value = answer.json().await.unwrap();
        assert_eq!(created["instance"], owner, "created through {k}: {created}");
    }
    for name in &sessions {
        let owner = fleet.id(fleet.owner(name)).to_string();
        for i in 0..3 {
            let url = fleet.instance(i).url(&format!("/v1/sessions/{name}"));
            let stats = get_until(&url, |_| true).await;
            assert_eq!(
                stats["instance"],
                owner,
                "{name} asked of {}: {stats}",
                fleet.id(i)
            );
        }
    }
    for i in 0..3 {
        let list = get_until(&fleet.instance(i).url("/v1/sessions"), |l| {
            l["sessions"].as_array().is_some_and(|s| s.len() == 6)
        })
        .await;
        for entry in list["sessions"].as_array().unwrap() {
            let name = entry["session"].as_str().unwrap();
            assert_eq!(
                entry["instance"],
                fleet.id(fleet.owner(name)),
                "the list of {}: {entry}",
                fleet.id(i)
            );
        }
    }

    // The session page's header names the owner (when a browser is at hand).
    let name = &sessions[0];
    let owner = fleet.id(fleet.owner(name)).to_string();
    match browser::install() {
        Err(reason) => eprintln!("skipping the web view part: no headless Chromium: {reason}"),
        Ok(()) => {
            let browser = Browser::start("fleet-owner").await;
            let ours = browser.identity();
            let other = (fleet.owner(name) + 1) % 3;
            browser
                .open(&fleet.instance(other).url(&format!("/sessions/{name}")))
                .await;
            let hooks = browser
                .wait_for(
                    &format!(
                        "(document.getElementById('stats') || {{innerText: ''}}).innerText.includes('instance {owner}')"
                    ),
                    "the owner in the header",
                )
                .await;
            println!("session page: {hooks}");
            drop(browser);
            assert!(survivors(&ours).is_empty());
        }
    }

    // kill -9 of an owner: its sessions are adopted, and say by whom.
    let victim = fleet.owner(name);
    fleet.kill(victim);
    let adopter = fleet.id(fleet.owner(name)).to_string();
    assert_ne!(adopter, fleet.id(victim));
    let survivor = fleet.running()[0];
    let url = fleet
        .instance(survivor)
        .url(&format!("/v1/sessions/{name}"));
    let stats = get_until(&url, |s| s["instance"] == adopter.as_str()).await;
    println!("adopted by {adopter}: {}", stats["instance"]);
}
