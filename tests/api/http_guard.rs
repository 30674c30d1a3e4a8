//! What a web page could make the operator's browser send is refused (catalogue rows T14–T16):
//! a foreign `Host` (DNS rebinding), a foreign `Origin` on anything that changes state, a body
//! that is not declared JSON on the JSON routes. And request heads hyper cannot take get the
//! JSON error body like every other refusal (T17). Raw sockets, so every header is exactly what
//! a browser (or attacker) would send.

use crate::common;

use std::time::Duration;

use common::server::{client, get, TestServer};
use serde_json::{json, Value};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// Sends `request` as is on a fresh connection and returns the status and the JSON body.
async fn raw(s: &TestServer, request: &[u8]) -> (u16, Value) {
    let address = s.http.trim_start_matches("http://");
    let mut stream = tokio::net::TcpStream::connect(address).await.unwrap();
    stream.write_all(request).await.unwrap();
    let mut answer = Vec::new();
    let read = tokio::time::timeout(Duration::from_secs(10), stream.read_to_end(&mut answer));
    read.await.expect("the server answers and closes").unwrap();
    let answer = String::from_utf8_lossy(&answer).into_owned();
    let (head, body) = answer.split_once("\r\n\r\n").expect("a response");
    let status = head.split(' ').nth(1).unwrap().parse().unwrap();
    let body = serde_json::from_str(body).unwrap_or(Value::String(body.into()));
    (status, body)
}

/// A request with `Connection: close`, the given headers and body.
fn request(method: &str, path: &str, headers: &[(&str, &str)], body: &str) -> Vec<u8> {
    let mut text = format!("{method} {path} HTTP/1.1\r\nConnection: close\r\n");
    for (k, v) in headers {
        text.push_str(&format!("{k}: {v}\r\n"));
    }
    text.push_str(&format!("Content-Length: {}\r\n\r\n{body}", body.len()));
    text.into_bytes()
}

fn expect(what: &str, (status, v): &(u16, Value), want: (u16, &str, Option<&str>)) {
    let got = (
        *status,
        v["error"]["code"].as_str().unwrap_or(""),
        v["error"]["field"].as_str(),
    );
    assert_eq!(got, want, "{what}: {v}");
    assert_eq!(v["error"]["status"], *status, "{what}: {v}");
}

#[tokio::test(flavor = "multi_thread")]
async fn cross_site_requests_are_refused_and_change_nothing() {
    let dir = common::temp_dir("guard");
    let config = dir.join("config.json");
    let lists = json!({"http": {"allowed_hosts": ["factord.lan"],
                                "allowed_origins": ["http://dashboard.lan:3000"]}});
    std::fs::write(&config, lists.to_string()).unwrap();
    let config = config.display().to_string();
    let s = TestServer::start(&["--no-zenoh", "--config", &config]);
    let own = s.http.trim_start_matches("http://").to_string();
    let own_origin = s.http.clone();
    let create = r#"{"session": "evil", "kind": "pose_graph_2d"}"#;
    let json_type = ("Content-Type", "application/json");

    // The hostile tester's exact probe: a foreign name, a foreign page, a form-safe type.
    let probe = [
        ("Host", "evil.example"),
        ("Origin", "http://evil.example"),
        ("Content-Type", "text/plain"),
    ];
    let answer = raw(&s, &request("POST", "/v1/sessions", &probe, create)).await;
    expect("the probe", &answer, (421, "forbidden_host", Some("host")));
    // DNS rebinding reads too: a GET under a foreign name.
    let rebound = [("Host", "evil.example:8080")];
    let answer = raw(&s, &request("GET", "/v1/sessions", &rebound, "")).await;
    expect(
        "rebinding GET",
        &answer,
        (421, "forbidden_host", Some("host")),
    );

    // Our own name, but a foreign page: every state-changing route, and the WebSocket.
    let foreign = [
        ("Host", own.as_str()),
        ("Origin", "http://evil.example"),
        json_type,
    ];
    for (method, path) in [
        ("POST", "/v1/sessions"),
        ("POST", "/v1/sessions/evil/batches"),
        ("PUT", "/v1/sessions/evil/auto_optimize"),
        ("DELETE", "/v1/sessions/evil"),
        ("POST", "/v1/jobs"),
    ] {
        let answer = raw(&s, &request(method, path, &foreign, create)).await;
        let what = format!("{method} {path} from a foreign origin");
        expect(&what, &answer, (403, "forbidden_origin", Some("origin")));
    }
    let upgrade = [
        ("Host", own.as_str()),
        ("Origin", "http://evil.example"),
        ("Upgrade", "websocket"),
        ("Sec-WebSocket-Version", "13"),
        ("Sec-WebSocket-Key", "dGhlIHNhbXBsZSBub25jZQ=="),
    ];
    let answer = raw(&s, &request("GET", "/v1/sessions/evil/ws", &upgrade, "")).await;
    expect(
        "WebSocket",
        &answer,
        (403, "forbidden_origin", Some("origin")),
    );

    // Same origin, but the body is not declared JSON: 415 naming the header.
    for content_type in [
        "text/plain",
        "application/x-www-form-urlencoded",
        "multipart/form-data; boundary=x",
    ] {
        let headers = [
            ("Host", own.as_str()),
            ("Origin", own_origin.as_str()),
            ("Content-Type", content_type),
        ];
        let answer = raw(&s, &request("POST", "/v1/sessions", &headers, create)).await;
        let want = (415, "unsupported_media_type", Some("content-type"));
        expect(content_type, &answer, want);
    }
    let untyped = [("Host", own.as_str())];
    let answer = raw(&s, &request("POST", "/v1/sessions", &untyped, create)).await;
    let want = (415, "unsupported_media_type", Some("content-type"));
    expect("no Content-Type", &answer, want);

    // Nothing of that was created.
    let (status, list) = get(&client(), &s.url("/v1/sessions")).await;
    assert_eq!(status, 200, "{list}");
    assert!(!list.to_string().contains("evil"), "{list}");

    // A same-origin page (the web view) and the allow-lists still work.
    let localhost = own.replace("127.0.0.1", "localhost");
    for (i, (host, origin)) in [
        (own.as_str(), own_origin.as_str()),
        (localhost.as_str(), "http://dashboard.lan:3000"),
        ("factord.lan:80", "http://factord.lan"),
    ]
    .into_iter()
    .enumerate()
    {
        let name = format!("allowed-{i}");
        let body = format!(r#"{{"session": "{name}", "kind": "pose_graph_2d"}}"#);
        let headers = [
            ("Host", host),
            ("Origin", origin),
            ("Content-Type", "application/json; charset=utf-8"),
        ];
        let (status, v) = raw(&s, &request("POST", "/v1/sessions", &headers, &body)).await;
        assert_eq!(status, 201, "{host} from {origin}: {v}");
    }
    // Graph files to /v1/jobs keep any type; programs send no Origin.
    let graph = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n";
    let headers = [("Host", own.as_str()), ("Content-Type", "text/plain")];
    let (status, v) = raw(&s, &request("POST", "/v1/jobs", &headers, graph)).await;
    assert_eq!(status, 200, "job: {v}");
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn unparseable_request_heads_get_the_json_error_body() {
    let s = TestServer::start(&["--no-zenoh"]);
    let long_uri = format!("/v1/health?{}", "a".repeat(70_000));
    let answer = raw(&s, &request("GET", &long_uri, &[("Host", "localhost")], "")).await;
    expect("long URI", &answer, (414, "uri_too_long", Some("uri")));

    let names: Vec<String> = (0..120).map(|i| format!("X-Header-{i}")).collect();
    let mut headers: Vec<(&str, &str)> = names.iter().map(|n| (n.as_str(), "1")).collect();
    headers.push(("Host", "localhost"));
    let answer = raw(&s, &request("GET", "/v1/health", &headers, "")).await;
    let want = (431, "headers_too_large", Some("headers"));
    expect("120 headers", &answer, want);

    let answer = raw(&s, b"NOT HTTP AT ALL\r\n\r\n").await;
    expect("garbage", &answer, (400, "malformed_request", None));

    // The server is still fine, and its own answers are untouched.
    let (status, v) = get(&client(), &s.url("/v1/health")).await;
    assert_eq!(status, 200, "{v}");
    let (status, v) = get(&client(), &s.url("/v1/nothing")).await;
    assert_eq!(
        (status, v["error"]["code"].as_str()),
        (404, Some("no_route"))
    );
    s.assert_no_panic();
}
