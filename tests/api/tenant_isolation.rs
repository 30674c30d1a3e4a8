//! Sessions belong to their token on every route and under every spelling of their name, and
//! zenoh peers reach only what the configured model lets them (issue 14, items 1 and 2).
//!
//! The URLs are sent on raw sockets: an HTTP client library may normalise percent-encoding
//! before it sends, and the attack is precisely a spelling the server decodes.

use crate::common;

use std::io::{Read, Write};
use std::time::{Duration, Instant};

use common::server::{client, free_port, zenoh_get, zenoh_peer, TestServer};
use serde_json::{json, Value};

const ALICE: &str = "alice-0123456789abcdef";
const BOB: &str = "bob-fedcba9876543210xyz";

/// One request on its own connection; the status and the body (as JSON when it is JSON).
/// Streaming routes answer with headers first: the body is read until `Connection: close`
/// ends it or 1 s passes.
fn raw(s: &TestServer, method: &str, path: &str, token: &str, body: &str) -> (u16, Value) {
    let host = s.http.trim_start_matches("http://");
    let mut stream = std::net::TcpStream::connect(host).expect("connects");
    stream
        .set_read_timeout(Some(Duration::from_secs(1)))
        .unwrap();
    let upgrade = if path.ends_with("/ws") {
        "Connection: Upgrade\r\nUpgrade: websocket\r\nSec-WebSocket-Version: 13\r\n\
         Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
    } else {
        "Connection: close\r\n"
    };
    let request = format!(
        "{method} {path} HTTP/1.1\r\nHost: {host}\r\nAuthorization: Bearer {token}\r\n\
         Content-Type: application/json\r\nContent-Length: {}\r\n{upgrade}\r\n{body}",
        body.len()
    );
    stream.write_all(request.as_bytes()).unwrap();
    let mut answer = Vec::new();
    let mut buf = [0u8; 8192];
    loop {
        match stream.read(&mut buf) {
            Ok(0) | Err(_) => break,
            Ok(n) => answer.extend_from_slice(&buf[..n]),
        }
    }
    let text = String::from_utf8_lossy(&answer);
    let status = text
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("{method} {path}: no status line in {text:?}"));
    let body = text.split_once("\r\n\r\n").map_or("", |(_, b)| b);
    (status, serde_json::from_str(body).unwrap_or(Value::Null))
}

fn start_with_tokens(extra: &[&str]) -> TestServer {
    let dir = common::temp_dir("tenants");
    let tokens = dir.join("tokens");
    std::fs::write(&tokens, format!("alice {ALICE}\nbob {BOB}\n")).unwrap();
    let mut args = vec!["--tokens-file", tokens.to_str().unwrap()];
    args.extend_from_slice(extra);
    TestServer::start_at(&dir.join("state"), &args, &[])
}

const BATCH: &str = r#"{"variables": [{"key": 0, "kind": "se2", "value": [0, 0, 0]},
    {"key": 1, "kind": "se2"}], "factors": [{"type": "between_se2", "keys": [0, 1],
    "measurement": [1, 0, 0.1], "information": [100, 0, 0, 100, 0, 400]}]}"#;

fn alice_creates_secret(s: &TestServer) {
    let create = r#"{"session": "secret", "kind": "pose_graph_2d"}"#;
    let (status, v) = raw(s, "POST", "/v1/sessions", ALICE, create);
    assert_eq!(status, 201, "{v}");
    let (status, v) = raw(
        s,
        "POST",
        "/v1/sessions/secret/batches?wait=true",
        ALICE,
        BATCH,
    );
    assert_eq!(status, 200, "{v}");
}

/// Every route that names a session, with a body where it takes one. DELETE comes last.
fn routes(name: &str) -> Vec<(&'static str, String, &'static str)> {
    let at = |rest: &str| format!("/v1/sessions/{name}{rest}");
    vec![
        ("GET", at(""), ""),
        ("GET", at("/estimate"), ""),
        ("GET", at("/summary"), ""),
        ("GET", at("/graph"), ""),
        ("GET", at("/marginals?keys=0"), ""),
        ("POST", at("/batches"), BATCH),
        ("POST", at("/fusion"), r#"{"messages": []}"#),
        ("POST", at("/optimize?wait=true"), ""),
        ("PUT", at("/auto_optimize"), r#"{"policy": "manual"}"#),
        ("POST", at("/cancel"), ""),
        ("GET", at("/events"), ""),
        ("GET", at("/ws"), ""),
        ("DELETE", at(""), ""),
    ]
}

#[test]
fn another_token_cannot_reach_a_session_under_any_spelling_of_its_name() {
    let s = start_with_tokens(&["--no-zenoh"]);
    alice_creates_secret(&s);
    let spellings = [
        "secret",
        "%73ecret",
        "%73%65%63%72%65%74",
        "secre%74",
        "%2573ecret",
        "secret%2F",
        "secret/",
    ];
    for name in spellings {
        for (method, path, body) in routes(name) {
            let (status, v) = raw(&s, method, &path, BOB, body);
            assert_eq!(status, 404, "bob: {method} {path} answered {status} {v}");
            let code = v["error"]["code"].as_str().unwrap_or_default();
            assert!(
                code == "unknown_session" || code == "no_route",
                "bob: {method} {path}: {v}"
            );
        }
    }
    // Nothing of bob's reached the session: one batch, both variables, journal in place.
    let (status, v) = raw(&s, "GET", "/v1/sessions/secret", ALICE, "");
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["num_variables"], 2, "{v}");
    assert_eq!(v["sequence"], 1, "{v}");
    assert!(s.state_dir.join("sessions/secret/journal.log").exists());
    // Nor is it listed or counted for bob, or for a caller without a token.
    let (_, list) = raw(&s, "GET", "/v1/sessions", BOB, "");
    assert_eq!(list["sessions"], json!([]), "{list}");
    let (_, health) = raw(&s, "GET", "/v1/health", "not-a-token", "");
    assert_eq!(health["sessions"], 0, "{health}");
    let (_, health) = raw(&s, "GET", "/v1/health", ALICE, "");
    assert_eq!(health["sessions"], 1, "{health}");

    // The spellings do reach the session for its owner: the check is on the decoded name.
    let (status, v) = raw(&s, "GET", "/v1/sessions/%73ecret/estimate", ALICE, "");
    assert_eq!(status, 200, "{v}");
    let (status, v) = raw(&s, "DELETE", "/v1/sessions/secre%74", ALICE, "");
    assert_eq!(status, 200, "{v}");
    s.assert_no_panic();
}

/// The web page of a session is served whatever the name to a caller without a token: a 404
/// for unknown names would tell strangers which sessions exist.
#[test]
fn the_session_page_does_not_tell_strangers_which_sessions_exist() {
    let s = start_with_tokens(&["--no-zenoh"]);
    alice_creates_secret(&s);
    let page = |name: &str| raw(&s, "GET", &format!("/sessions/{name}"), "none", "").0;
    assert_eq!(page("secret"), page("never-created"));
}

async fn zenoh_until_connected(endpoint: &str) -> zenoh::Session {
    let z = zenoh_peer(endpoint).await;
    // The peer is connected once the service's rpc answers.
    zenoh_get(&z, "factord/rpc", Some(&json!({"op": "health"})))
        .await
        .expect("health over zenoh");
    z
}

#[tokio::test(flavor = "multi_thread")]
async fn anonymous_zenoh_peers_reach_only_unowned_sessions_and_the_operator_is_told() {
    let s = start_with_tokens(&[]);
    alice_creates_secret(&s);
    let z = zenoh_until_connected(&s.zenoh).await;
    let events = z.declare_subscriber("factord/secret/out/**").await.unwrap();
    let binary = z.declare_subscriber("factord/secret/bin/**").await.unwrap();

    let sessions = zenoh_get(&z, "factord/rpc", Some(&json!({"op": "list_sessions"})))
        .await
        .unwrap();
    assert_eq!(sessions["sessions"], json!([]), "{sessions}");
    for command in [
        json!({"op": "get_estimate", "session": "secret"}),
        json!({"op": "get_stats", "session": "secret"}),
        json!({"op": "optimize", "session": "secret", "wait": true}),
        json!({"op": "delete_session", "session": "secret"}),
    ] {
        let e = zenoh_get(&z, "factord/rpc", Some(&command))
            .await
            .unwrap_err();
        assert_eq!(e["error"]["status"], 404, "{command}: {e}");
        assert_eq!(e["error"]["code"], "unknown_session", "{command}: {e}");
    }
    let e = zenoh_get(&z, "factord/secret/estimate", None)
        .await
        .unwrap_err();
    assert_eq!(e["error"]["status"], 404, "{e}");
    let put = json!({"variables": [{"key": 2, "kind": "se2", "value": [2, 0, 0]}]});
    z.put("factord/secret/in/batch", put.to_string())
        .await
        .unwrap();

    // alice's own writes are not published where any peer could subscribe.
    let (status, _) = raw(
        &s,
        "POST",
        "/v1/sessions/secret/optimize?wait=true",
        ALICE,
        "",
    );
    assert_eq!(status, 200);
    tokio::time::sleep(Duration::from_millis(500)).await;
    let (status, v) = raw(&s, "GET", "/v1/sessions/secret", ALICE, "");
    assert_eq!(status, 200, "{v}");
    assert_eq!(
        v["num_variables"], 2,
        "the zenoh put reached alice's session: {v}"
    );
    while let Ok(Some(sample)) = events.try_recv() {
        let text = String::from_utf8_lossy(&sample.payload().to_bytes()).into_owned();
        assert!(
            sample.key_expr().as_str() == "factord/secret/out/errors"
                && text.contains("unknown_session"),
            "published for an owned session: {} {text}",
            sample.key_expr()
        );
    }
    if let Ok(Some(sample)) = binary.try_recv() {
        panic!("published for an owned session: {}", sample.key_expr());
    }

    // Sessions created over zenoh are unowned: zenoh peers and every token reach them.
    let created = zenoh_get(
        &z,
        "factord/rpc",
        Some(&json!({"op": "create_session", "session": "open-1", "kind": "pose_graph_2d"})),
    )
    .await
    .unwrap();
    assert_eq!(created["session"], "open-1", "{created}");
    assert_eq!(raw(&s, "GET", "/v1/sessions/open-1", BOB, "").0, 200);
    assert!(
        s.stderr().contains("zenoh peers are anonymous"),
        "no warning at start: {}",
        s.stderr()
    );
    z.close().await.unwrap();
    s.assert_no_panic();
}

/// zenoh with user/password authentication, mapped to alice: an authenticated peer reaches
/// alice's sessions (not bob's); a peer without the password reaches nothing.
#[tokio::test(flavor = "multi_thread")]
async fn authenticated_zenoh_acts_as_its_principal() {
    let dir = common::temp_dir("zenoh-usrpwd");
    let dictionary = dir.join("users");
    std::fs::write(&dictionary, "robot:s3cret-pass\n").unwrap();
    let config = dir.join("zenoh.json5");
    let usrpwd = format!(
        "{{transport: {{auth: {{usrpwd: {{dictionary_file: {:?}}}}}}}}}",
        dictionary.display().to_string()
    );
    std::fs::write(&config, usrpwd).unwrap();
    let config = config.to_str().unwrap();

    // The principal without zenoh authentication is refused at start.
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_factord"))
        .args(["serve", "--listen", "127.0.0.1:0", "--no-journal"])
        .args(["--zenoh-listen", &format!("tcp/127.0.0.1:{}", free_port())])
        .args(["--zenoh-multicast", "off", "--zenoh-principal", "alice"])
        .env("FACTORD_TOKENS", ALICE)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("zenoh.principal"), "{stderr}");

    let s = start_with_tokens(&["--zenoh-config", config, "--zenoh-principal", "alice"]);
    alice_creates_secret(&s);
    let bobs = r#"{"session": "bobs", "kind": "pose_graph_2d"}"#;
    assert_eq!(raw(&s, "POST", "/v1/sessions", BOB, bobs).0, 201);

    let mut c = zenoh::Config::default();
    for (key, value) in [
        ("mode", "\"peer\"".to_string()),
        ("scouting/multicast/enabled", "false".into()),
        ("connect/endpoints", format!("[\"{}\"]", s.zenoh)),
        ("transport/auth/usrpwd/user", "\"robot\"".into()),
        ("transport/auth/usrpwd/password", "\"s3cret-pass\"".into()),
    ] {
        c.insert_json5(key, &value).unwrap();
    }
    let z = zenoh::open(c).await.unwrap();
    let list = zenoh_get(&z, "factord/rpc", Some(&json!({"op": "list_sessions"})))
        .await
        .unwrap();
    let names: Vec<_> = list["sessions"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["session"].clone())
        .collect();
    assert_eq!(names, vec![json!("secret")], "{list}");
    let estimate = zenoh_get(&z, "factord/secret/estimate", None)
        .await
        .unwrap();
    assert_eq!(
        estimate["variables"].as_array().map(Vec::len),
        Some(2),
        "{estimate}"
    );
    let e = zenoh_get(&z, "factord/bobs/estimate", None)
        .await
        .unwrap_err();
    assert_eq!(e["error"]["status"], 404, "{e}");

    // Without the password the peer never gets a link: no reply within 3 s.
    let stranger = zenoh_peer(&s.zenoh).await;
    let deadline = Instant::now() + Duration::from_secs(3);
    while Instant::now() < deadline {
        let replies = stranger
            .get("factord/rpc")
            .payload(json!({"op": "list_sessions"}).to_string())
            .timeout(Duration::from_millis(500))
            .await
            .unwrap();
        assert!(
            replies.recv_async().await.is_err(),
            "an unauthenticated peer got a reply"
        );
    }
    z.close().await.unwrap();
    stranger.close().await.unwrap();
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn zenoh_and_http_share_one_caller_model_without_tokens() {
    // Without tokens (loopback), both transports see everything, as before.
    let s = TestServer::start(&[]);
    let c = client();
    common::server::create(
        &c,
        &s,
        &json!({"session": "shared", "kind": "pose_graph_2d"}),
    )
    .await;
    let z = zenoh_until_connected(&s.zenoh).await;
    let stats = zenoh_get(
        &z,
        "factord/rpc",
        Some(&json!({"op": "get_stats", "session": "shared"})),
    )
    .await
    .unwrap();
    assert_eq!(stats["session"], "shared", "{stats}");
    assert!(!s.stderr().contains("zenoh peers are anonymous"));
    z.close().await.unwrap();
}
