//! Bearer tokens over real sockets: 401 without one, sessions owned by the token that created
//! them (404 to every other token, also after a restart), required beyond loopback.

use crate::common;

use std::process::{Command, Stdio};
use std::time::Duration;

use common::server::{client, TestServer};
use serde_json::{json, Value};

const ALICE: &str = "alice-0123456789abcdef";
const BOB: &str = "bob-fedcba9876543210xyz";

async fn call(
    c: &reqwest::Client,
    method: reqwest::Method,
    url: &str,
    token: Option<&str>,
    body: Option<Value>,
) -> (u16, Value, reqwest::header::HeaderMap) {
    let mut request = c.request(method, url);
    if let Some(t) = token {
        request = request.bearer_auth(t);
    }
    if let Some(b) = body {
        request = request.json(&b);
    }
    let response = request.send().await.unwrap();
    let status = response.status().as_u16();
    let headers = response.headers().clone();
    let text = response.text().await.unwrap();
    (
        status,
        serde_json::from_str(&text).unwrap_or(Value::String(text)),
        headers,
    )
}

#[tokio::test(flavor = "multi_thread")]
async fn tokens_guard_every_route_and_sessions_belong_to_their_token() {
    let dir = common::temp_dir("auth");
    let tokens = dir.join("tokens");
    std::fs::write(&tokens, format!("# who\nalice {ALICE}\nbob {BOB}\n")).unwrap();
    let tokens = tokens.display().to_string();
    let state = dir.join("state");
    let s = TestServer::start_at(
        &state,
        &["--no-zenoh", "--tokens-file", &tokens, "--operators", "bob"],
        &[],
    );
    let c = client();
    use reqwest::Method as M;

    // Health stays open (liveness probes); everything else needs a valid token.
    assert_eq!(
        call(&c, M::GET, &s.url("/v1/health"), None, None).await.0,
        200
    );
    for (method, path) in [
        (M::GET, "/v1/sessions"),
        (M::POST, "/v1/sessions"),
        (M::GET, "/v1/sessions/x/estimate"),
        (M::POST, "/v1/jobs"),
        (M::GET, "/metrics"),
    ] {
        let (status, v, headers) = call(&c, method.clone(), &s.url(path), None, None).await;
        assert_eq!(status, 401, "{method} {path}: {v}");
        assert_eq!(v["error"]["code"], "unauthorized");
        assert_eq!(headers["www-authenticate"], "Bearer");
        let (status, v, _) = call(
            &c,
            method.clone(),
            &s.url(path),
            Some("wrong-token-0000000000"),
            None,
        )
        .await;
        assert_eq!(status, 401, "{method} {path}: {v}");
        assert!(v["error"]["message"]
            .as_str()
            .unwrap()
            .contains("not valid"));
    }

    let create = json!({"session": "alices", "kind": "pose_graph_2d"});
    let (status, v, _) = call(
        &c,
        M::POST,
        &s.url("/v1/sessions"),
        Some(ALICE),
        Some(create),
    )
    .await;
    assert_eq!(status, 201, "{v}");
    let batch = json!({"variables": [{"key": 0, "kind": "se2", "value": [0, 0, 0]}]});
    let url = s.url("/v1/sessions/alices/batches");
    assert_eq!(
        call(&c, M::POST, &url, Some(ALICE), Some(batch.clone()))
            .await
            .0,
        200
    );

    // To bob, alice's session is exactly like one that does not exist.
    let (status, theirs, _) =
        call(&c, M::GET, &s.url("/v1/sessions/alices"), Some(BOB), None).await;
    let (_, missing, _) = call(&c, M::GET, &s.url("/v1/sessions/nobody"), Some(BOB), None).await;
    assert_eq!(status, 404);
    assert_eq!(
        theirs["error"]["message"]
            .as_str()
            .unwrap()
            .replace("alices", "X"),
        missing["error"]["message"]
            .as_str()
            .unwrap()
            .replace("nobody", "X")
    );
    assert_eq!(
        call(&c, M::POST, &url, Some(BOB), Some(batch.clone()))
            .await
            .0,
        404
    );
    let delete = s.url("/v1/sessions/alices");
    assert_eq!(call(&c, M::DELETE, &delete, Some(BOB), None).await.0, 404);
    let (_, list, _) = call(&c, M::GET, &s.url("/v1/sessions"), Some(BOB), None).await;
    assert_eq!(list["sessions"], json!([]));
    let (_, list, _) = call(&c, M::GET, &s.url("/v1/sessions"), Some(ALICE), None).await;
    assert_eq!(list["sessions"][0]["session"], "alices");
    // Server-wide figures are the operator's (bob here), not every tenant's (A12).
    let (status, metrics, _) = call(&c, M::GET, &s.url("/metrics"), Some(BOB), None).await;
    assert_eq!(status, 200);
    let metrics = metrics.as_str().unwrap();
    assert!(metrics.contains("factord_rejected_inputs_total{reason=\"unauthorized\"}"));
    assert!(metrics.contains("\nfactord_sessions 1\n"), "{metrics}");
    let (status, v, _) = call(&c, M::GET, &s.url("/metrics"), Some(ALICE), None).await;
    assert_eq!(status, 403, "{v}");
    assert_eq!(v["error"]["code"], "operator_only");
    assert_eq!(v["error"]["field"], "authorization");
    assert!(!v.to_string().contains("factord_sessions"));
    s.assert_no_panic();
    s.kill();

    // Ownership is part of the session's durable record.
    let s = TestServer::start_at(&state, &["--no-zenoh", "--tokens-file", &tokens], &[]);
    let stats = s.url("/v1/sessions/alices");
    let mut waited = 0;
    loop {
        let (status, v, _) = call(&c, M::GET, &stats, Some(ALICE), None).await;
        assert_eq!(status, 200, "{v}");
        if v["recovering"] == false {
            assert_eq!(v["num_variables"], 1);
            break;
        }
        waited += 1;
        assert!(waited < 500, "still recovering");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    assert_eq!(call(&c, M::GET, &stats, Some(BOB), None).await.0, 404);
    s.assert_no_panic();
}

#[test]
fn beyond_loopback_tokens_are_required() {
    let state = common::temp_dir("auth-open");
    // `factord serve` on every interface with FACTORD_TOKENS as given: it must refuse to start.
    let refusal = |tokens: Option<&str>| {
        let mut serve = Command::new(env!("CARGO_BIN_EXE_factord"));
        serve
            .args([
                "serve",
                "--listen",
                "0.0.0.0:0",
                "--no-zenoh",
                "--state-dir",
            ])
            .arg(&state)
            .stdout(Stdio::null());
        match tokens {
            Some(list) => serve.env("FACTORD_TOKENS", list),
            None => serve.env_remove("FACTORD_TOKENS"),
        };
        let out = serve.output().unwrap();
        assert!(!out.status.success());
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let stderr = refusal(None);
    assert!(stderr.contains("requires bearer tokens"), "{stderr}");
    // A token too short to be safe is refused as well.
    assert!(refusal(Some("short")).contains("at least 16"));
}

/// `/metrics` without an operator list: a single label is its own operator; several labels
/// leave it closed (and the server says so); a list naming an unknown label stops the start.
#[tokio::test(flavor = "multi_thread")]
async fn metrics_answer_the_operator_only() {
    let dir = common::temp_dir("auth-operators");
    let c = client();
    let metrics = |s: &TestServer| s.url("/metrics");

    let one = dir.join("one");
    std::fs::write(&one, format!("alice {ALICE}\n")).unwrap();
    let s = TestServer::start_at(
        &dir.join("state-one"),
        &["--no-zenoh", "--tokens-file", one.to_str().unwrap()],
        &[],
    );
    let (status, _, _) = call(&c, reqwest::Method::GET, &metrics(&s), Some(ALICE), None).await;
    assert_eq!(status, 200);
    s.kill();

    let two = dir.join("two");
    std::fs::write(&two, format!("alice {ALICE}\nbob {BOB}\n")).unwrap();
    let s = TestServer::start_at(
        &dir.join("state-two"),
        &["--no-zenoh", "--tokens-file", two.to_str().unwrap()],
        &[],
    );
    for token in [ALICE, BOB] {
        let (status, v, _) = call(&c, reqwest::Method::GET, &metrics(&s), Some(token), None).await;
        assert_eq!(
            (status, &v["error"]["code"]),
            (403, &json!("operator_only"))
        );
    }
    assert!(s
        .stderr()
        .contains("GET /metrics answers 403 to every token"));
    s.kill();

    let out = Command::new(env!("CARGO_BIN_EXE_factord"))
        .args([
            "serve",
            "--no-zenoh",
            "--listen",
            "127.0.0.1:0",
            "--state-dir",
        ])
        .arg(dir.join("state-three"))
        .args([
            "--tokens-file",
            two.to_str().unwrap(),
            "--operators",
            "carol",
        ])
        .stdout(Stdio::null())
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("`carol`, which is the label of no token"),
        "{stderr}"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn tokens_from_the_environment_beyond_loopback() {
    let state = common::temp_dir("auth-env");
    // Listening on every interface; reached over loopback here.
    let s = TestServer::start_at(
        &state,
        &["--no-zenoh", "--listen", "0.0.0.0:0"],
        &[("FACTORD_TOKENS", ALICE)],
    );
    let port = s.http.rsplit(':').next().unwrap().to_string();
    let url = format!("http://127.0.0.1:{port}/v1/sessions");
    let c = client();
    assert_eq!(
        call(&c, reqwest::Method::GET, &url, None, None).await.0,
        401
    );
    assert_eq!(
        call(&c, reqwest::Method::GET, &url, Some(ALICE), None)
            .await
            .0,
        200
    );
}

/// The web view's login: a valid token is exchanged for an `HttpOnly; SameSite=Strict` cookie
/// that reads (GET, the event stream) like the bearer header, but changes nothing: a cross-site
/// form or a WebSocket (which takes batches) cannot use it. A bad token is 401 naming `token`.
#[tokio::test(flavor = "multi_thread")]
async fn the_login_cookie_reads_but_never_writes() {
    let dir = common::temp_dir("auth-cookie");
    let tokens = dir.join("tokens");
    std::fs::write(&tokens, format!("alice {ALICE}\nbob {BOB}\n")).unwrap();
    let tokens = tokens.display().to_string();
    let s = TestServer::start_at(
        &dir.join("state"),
        &["--no-zenoh", "--tokens-file", &tokens],
        &[],
    );
    let c = client();
    use reqwest::Method as M;
    let login = s.url("/v1/login");

    let (status, v, _) = call(
        &c,
        M::POST,
        &login,
        None,
        Some(json!({"token": "x".repeat(20)})),
    )
    .await;
    assert_eq!(status, 401, "{v}");
    assert_eq!(v["error"]["field"], "token");
    let (status, v, _) = call(&c, M::POST, &login, None, Some(json!({"tokn": ALICE}))).await;
    assert_eq!(status, 400, "{v}");
    assert_eq!(v["error"]["field"], "tokn");

    let (status, v, headers) = call(&c, M::POST, &login, None, Some(json!({"token": ALICE}))).await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(v, json!({"auth": true, "principal": "alice"}));
    let set = headers["set-cookie"].to_str().unwrap().to_string();
    assert!(
        set.contains("HttpOnly") && set.contains("SameSite=Strict"),
        "{set}"
    );
    assert!(
        !set.contains(ALICE),
        "the cookie holds the token encoded: {set}"
    );
    let cookie = set.split(';').next().unwrap().to_string();

    let create = json!({"session": "alices", "kind": "pose_graph_2d"});
    let (status, v, _) = call(
        &c,
        M::POST,
        &s.url("/v1/sessions"),
        Some(ALICE),
        Some(create),
    )
    .await;
    assert_eq!(status, 201, "{v}");
    let with_cookie = |method: M, path: &str| {
        c.request(method, s.url(path))
            .header("cookie", format!("theme=dark; {cookie}"))
    };
    // Reads: the list, stats, history and the event stream.
    for path in [
        "/v1/sessions",
        "/v1/sessions/alices",
        "/v1/sessions/alices/history",
    ] {
        let r = with_cookie(M::GET, path).send().await.unwrap();
        assert_eq!(r.status(), 200, "GET {path}");
    }
    let v: Value = with_cookie(M::GET, "/v1/sessions")
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(v["sessions"][0]["session"], "alices");
    let events = with_cookie(M::GET, "/v1/sessions/alices/events")
        .send()
        .await
        .unwrap();
    assert_eq!(events.status(), 200);
    drop(events);
    // Writes: refused with the cookie alone, whatever the method.
    let batch = json!({"variables": [{"key": 0, "kind": "se2", "value": [0, 0, 0]}]});
    let r = with_cookie(M::POST, "/v1/sessions/alices/batches")
        .json(&batch)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 401);
    let r = with_cookie(M::DELETE, "/v1/sessions/alices")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 401);
    let r = with_cookie(M::GET, "/v1/sessions/alices/ws")
        .header("connection", "upgrade")
        .header("upgrade", "websocket")
        .header("sec-websocket-version", "13")
        .header("sec-websocket-key", "dGhlIHNhbXBsZSBub25jZQ==")
        .send()
        .await
        .unwrap();
    assert_eq!(
        r.status(),
        401,
        "a WebSocket takes batches: no cookie for it"
    );
    // Bob's cookie does not see alice's session; a forged cookie is no one's.
    let (_, _, headers) = call(&c, M::POST, &login, None, Some(json!({"token": BOB}))).await;
    let bob = headers["set-cookie"]
        .to_str()
        .unwrap()
        .split(';')
        .next()
        .unwrap()
        .to_string();
    let r = c
        .get(s.url("/v1/sessions/alices"))
        .header("cookie", bob)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 404);
    let r = c
        .get(s.url("/v1/sessions"))
        .header("cookie", "factord_token=zz")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 401);
    // Logging out clears it.
    let (status, _, headers) = call(&c, M::POST, &s.url("/v1/logout"), None, None).await;
    assert_eq!(status, 204);
    assert!(headers["set-cookie"]
        .to_str()
        .unwrap()
        .contains("Max-Age=0"));
    s.assert_no_panic();
}
