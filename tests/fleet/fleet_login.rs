//! The web view's login cookie in a fleet (issue 52, item 8): the cookie names a login only the
//! instance that set it knows, so a read it authenticates, for a session another instance owns,
//! is forwarded with a bearer token of the same principal, and the list includes every
//! instance's sessions.

use crate::common;

use std::time::Duration;

use common::fleet::Fleet;
use common::server::zenoh_peer;
use serde_json::{json, Value};

const ALICE: &str = "alice-0123456789abcdef";

#[tokio::test(flavor = "multi_thread")]
async fn a_cookie_reads_sessions_owned_by_another_instance() {
    let tokens = common::temp_dir("fleet-login").join("tokens");
    std::fs::write(&tokens, format!("alice {ALICE}\n")).unwrap();
    let fleet = Fleet::start(2, &["--tokens-file", &tokens.display().to_string()]);
    let z = zenoh_peer(&fleet.instance(0).zenoh).await;
    fleet.wait_settled(&z).await;
    let c = reqwest::Client::builder()
        .timeout(Duration::from_secs(20))
        .build()
        .unwrap();
    let names: Vec<String> = (0..6).map(|i| format!("robot-{i}")).collect();
    for name in &names {
        let r = c
            .post(fleet.instance(0).url("/v1/sessions"))
            .bearer_auth(ALICE)
            .json(&json!({"session": name, "kind": "pose_graph_2d"}))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 201, "{name}\n{}", fleet.logs());
    }
    let login = c
        .post(fleet.instance(0).url("/v1/login"))
        .json(&json!({ "token": ALICE }))
        .send()
        .await
        .unwrap();
    let cookie = login.headers()["set-cookie"].to_str().unwrap();
    let cookie = cookie.split(';').next().unwrap().to_string();
    let remote = names
        .iter()
        .find(|n| fleet.owner(n) == 1)
        .expect("one on f2");
    let r = c
        .get(fleet.instance(0).url(&format!("/v1/sessions/{remote}")))
        .header("cookie", &cookie)
        .send()
        .await
        .unwrap();
    assert_eq!(
        r.status(),
        200,
        "a read of {remote} on f2 through f1 with f1's cookie"
    );
    let list: Value = c
        .get(fleet.instance(0).url("/v1/sessions"))
        .header("cookie", &cookie)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let listed = list["sessions"].as_array().map_or(0, |l| l.len());
    assert_eq!(listed, names.len(), "{list}");
}
