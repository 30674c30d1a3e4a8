//! Logins and tokens against a real `factord serve` with tokens on, over real sockets (issue 52,
//! item 8; catalogue rows A9–A11): a token is the exact string, a wrong bearer token is never
//! rescued by a valid cookie, the cookie is an opaque login id that logout revokes (and
//! `Secure` behind TLS), and a peer's failed attempts are throttled, counted in a metric.

use crate::common;

use std::net::{IpAddr, Ipv4Addr};
use std::time::Duration;

use common::server::{client, TestServer};
use serde_json::{json, Value};

const ALICE: &str = "alice-0123456789abcdef";

fn server() -> TestServer {
    let dir = common::temp_dir("login-hardening");
    let tokens = dir.join("tokens");
    std::fs::write(&tokens, format!("alice {ALICE}\n")).unwrap();
    TestServer::start(&["--no-zenoh", "--tokens-file", &tokens.display().to_string()])
}

/// A client whose connections come from `source` (any 127.x address is this machine).
fn client_from(source: Ipv4Addr) -> reqwest::Client {
    reqwest::Client::builder()
        .local_address(IpAddr::V4(source))
        .timeout(Duration::from_secs(10))
        .build()
        .unwrap()
}

/// `POST /v1/login` with `token`: status, body and the cookie set (name=value), if any.
async fn login(c: &reqwest::Client, s: &TestServer, token: &str) -> (u16, Value, Option<String>) {
    let response = c
        .post(s.url("/v1/login"))
        .json(&json!({ "token": token }))
        .send()
        .await
        .unwrap();
    let status = response.status().as_u16();
    let cookie = response
        .headers()
        .get("set-cookie")
        .and_then(|v| v.to_str().ok())
        .map(|v| v.split(';').next().unwrap_or("").to_string());
    (status, response.json().await.unwrap_or(Value::Null), cookie)
}

async fn list_with(c: &reqwest::Client, s: &TestServer, cookie: &str, bearer: Option<&str>) -> u16 {
    let mut request = c.get(s.url("/v1/sessions")).header("cookie", cookie);
    if let Some(bearer) = bearer {
        request = request.header("authorization", bearer);
    }
    request.send().await.unwrap().status().as_u16()
}

#[tokio::test(flavor = "multi_thread")]
async fn tokens_are_exact_and_the_cookie_is_an_opaque_revocable_login() {
    let s = server();
    let c = client();

    // The token with anything around it is another token, in a login or a bearer header.
    for padded in [
        format!(" {ALICE}"),
        format!("{ALICE}\n"),
        format!("\t{ALICE} "),
    ] {
        let (status, v, _) = login(&c, &s, &padded).await;
        assert_eq!(status, 401, "login with {padded:?}: {v}");
    }
    let status = c
        .get(s.url("/v1/sessions"))
        .header("authorization", format!("Bearer  {ALICE}"))
        .send()
        .await
        .unwrap()
        .status();
    assert_eq!(status, 401, "a bearer token with a space before it");

    // The cookie names a login, not the token: nothing in it decodes to the token.
    let (status, v, cookie) = login(&c, &s, ALICE).await;
    assert_eq!(status, 200, "{v}");
    let cookie = cookie.expect("a cookie");
    let value = cookie.split_once('=').map_or("", |(_, v)| v);
    let decoded = hex::decode(value).unwrap_or_default();
    assert!(
        !String::from_utf8_lossy(&decoded).contains(ALICE) && !value.contains(ALICE),
        "the cookie carries the token: {cookie}"
    );
    assert_eq!(list_with(&c, &s, &cookie, None).await, 200);

    // A wrong bearer token is refused even with a valid cookie beside it.
    let wrong = "Bearer wrong-token-0000000000";
    assert_eq!(list_with(&c, &s, &cookie, Some(wrong)).await, 401);

    // Logging out ends the login: the same cookie reads nothing any more.
    let r = c
        .post(s.url("/v1/logout"))
        .header("cookie", &cookie)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 204);
    assert_eq!(list_with(&c, &s, &cookie, None).await, 401);

    // Behind TLS (the proxy says so) the cookie is Secure.
    let r = c
        .post(s.url("/v1/login"))
        .header("x-forwarded-proto", "https")
        .json(&json!({ "token": ALICE }))
        .send()
        .await
        .unwrap();
    let set = r.headers()["set-cookie"].to_str().unwrap().to_string();
    assert!(set.contains("; Secure"), "{set}");
    s.assert_no_panic();
}

/// The value of an unlabelled counter in the exposition text.
fn counter(metrics: &str, name: &str) -> f64 {
    metrics
        .lines()
        .find_map(|l| l.strip_prefix(name)?.trim().parse().ok())
        .unwrap_or(0.0)
}

#[tokio::test(flavor = "multi_thread")]
async fn a_peers_failed_attempts_are_throttled_and_counted() {
    let s = server();
    let attacker = client_from(Ipv4Addr::new(127, 0, 0, 1));
    let bystander = client_from(Ipv4Addr::new(127, 0, 0, 2));

    // A stale login cookie (a restart, a logout) is refused but spends nothing: it is a random
    // id, not a guess, and a browser polling with one must not lock its address out.
    for _ in 0..25 {
        assert_eq!(
            list_with(&attacker, &s, "factord_session=00ff", None).await,
            401
        );
    }

    // Wrong logins and wrong bearer tokens from one address: after 20, 429 with Retry-After.
    let mut statuses = Vec::new();
    for i in 0..15 {
        statuses.push(login(&attacker, &s, &format!("guess-{i:016}")).await.0);
        let r = attacker
            .get(s.url("/v1/sessions"))
            .bearer_auth(format!("guess-{i:016}"))
            .send()
            .await
            .unwrap();
        statuses.push(r.status().as_u16());
    }
    println!("statuses: {statuses:?}");
    assert!(statuses[..20].iter().all(|s| *s == 401), "{statuses:?}");
    assert!(statuses[20..].iter().all(|s| *s == 429), "{statuses:?}");

    // Throttled, even the right token is not looked at; the answer names the field.
    let r = attacker
        .get(s.url("/v1/sessions"))
        .bearer_auth(ALICE)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 429);
    assert!(r.headers().contains_key("retry-after"));
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["error"]["code"], "too_many_failures", "{v}");
    assert_eq!(v["error"]["field"], "authorization", "{v}");
    let (status, v, _) = login(&attacker, &s, ALICE).await;
    assert_eq!(status, 429, "{v}");

    // Another address is unaffected, and sees the failures in the metrics.
    let r = bystander
        .get(s.url("/metrics"))
        .bearer_auth(ALICE)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let metrics = r.text().await.unwrap();
    let failures = counter(&metrics, "factord_http_auth_failures_total");
    assert_eq!(failures, 20.0, "{metrics}");
    assert!(
        metrics.contains("factord_rejected_inputs_total{reason=\"too_many_failures\"}"),
        "{metrics}"
    );
    s.assert_no_panic();
}
