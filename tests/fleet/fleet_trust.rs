//! A fleet's instances prove membership with a shared secret (issue 52, item 2).
//!
//! Before, a plain zenoh session that declared `factord/@fleet/<id>` and answered its `info`
//! with a URL of its own was taken into placement: it received creations and session lists
//! with tenants' bearer tokens, its fake sessions and estimates were served to them. Here such
//! a rogue peer sits in a two-instance fleet with tokens on (with the smallest id, so it would
//! also have been elected rpc gateway) and gets nothing: no HTTP connection, no forwarded
//! command, no place in the membership or the lists. A forged caller assertion is refused, and
//! a fleet without a secret refuses to start unless told its network is trusted.

use crate::common;

use std::io::{Read, Write};
use std::net::TcpListener;
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use common::fleet::{infos, Fleet};
use common::server::{client, free_port, zenoh_peer};
use serde_json::{json, Value};

const ALICE: &str = "alice-token-0123456789abcdef";
const BOB: &str = "bob-token-0123456789abcdef";

/// A rogue HTTP server: accepts every connection, keeps what was sent, answers a fake estimate.
struct RogueHttp {
    url: String,
    received: Arc<Mutex<Vec<String>>>,
}

impl RogueHttp {
    fn start() -> Self {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        let received = Arc::new(Mutex::new(Vec::new()));
        let kept = Arc::clone(&received);
        std::thread::spawn(move || {
            for stream in listener.incoming() {
                let Ok(mut stream) = stream else { return };
                let _ = stream.set_read_timeout(Some(Duration::from_millis(500)));
                let mut buf = vec![0u8; 64 << 10];
                let n = stream.read(&mut buf).unwrap_or(0);
                kept.lock()
                    .unwrap()
                    .push(String::from_utf8_lossy(&buf[..n]).into_owned());
                let body = r#"{"session":"x","sequence":424242,"variables":[]}"#;
                let _ = write!(
                    stream,
                    "HTTP/1.1 200 OK\r\ncontent-type: application/json\r\ncontent-length: {}\r\n\r\n{body}",
                    body.len()
                );
            }
        });
        Self { url, received }
    }

    fn requests(&self) -> Vec<String> {
        self.received.lock().unwrap().clone()
    }
}

/// A zenoh peer that announces itself as fleet instance `0rogue` (smaller than any `f<n>`),
/// ready and serving as gateway, answers its `info` with `http` and a fake session, and counts
/// the commands forwarded to it.
struct RoguePeer {
    _tokens: Vec<zenoh::liveliness::LivelinessToken>,
    _queryables: Vec<zenoh::query::Queryable<()>>,
    forwarded: Arc<AtomicUsize>,
}

impl RoguePeer {
    async fn join(z: &zenoh::Session, http: &str) -> Self {
        let mut tokens = Vec::new();
        for key in [
            "factord/@fleet/0rogue",
            "factord/@fleet/0rogue/ready",
            "factord/@fleet/0rogue/gateway",
        ] {
            tokens.push(z.liveliness().declare_token(key).await.unwrap());
        }
        let info = json!({"instance": "0rogue", "http": http, "settled": true,
            "live": {"0rogue": http}, "rpc_gateway": true,
            "sessions": [{"session": "rogue-session", "kind": "pose_graph_2d", "sequence": 424242}],
            "load": {"sessions": 1, "busy_workers": 0, "queued": 0}})
        .to_string();
        let info_queryable = z
            .declare_queryable("factord/@fleet/0rogue/info")
            .callback(move |query| {
                let _ = zenoh::Wait::wait(query.reply("factord/@fleet/0rogue/info", info.clone()));
            })
            .await
            .unwrap();
        let forwarded = Arc::new(AtomicUsize::new(0));
        let counter = Arc::clone(&forwarded);
        let rpc = z
            .declare_queryable("factord/@fleet/0rogue/rpc")
            .callback(move |query| {
                counter.fetch_add(1, Ordering::SeqCst);
                let fake = r#"{"session":"x","sequence":424242}"#;
                let _ = zenoh::Wait::wait(query.reply(query.key_expr().clone(), fake));
            })
            .await
            .unwrap();
        Self {
            _tokens: tokens,
            _queryables: vec![info_queryable, rpc],
            forwarded,
        }
    }
}

/// A request with `token`, repeated while a session moves (503); the status and JSON answer.
async fn send(
    c: &reqwest::Client,
    method: reqwest::Method,
    url: &str,
    token: &str,
    body: Option<Value>,
) -> (u16, Value) {
    let deadline = Instant::now() + Duration::from_secs(15);
    loop {
        let mut request = c.request(method.clone(), url).bearer_auth(token);
        if let Some(b) = &body {
            request = request
                .header("content-type", "application/json")
                .body(b.to_string());
        }
        let answer = request.send().await.unwrap();
        let status = answer.status().as_u16();
        let v: Value = answer.json().await.unwrap_or(Value::Null);
        if status != 503 || Instant::now() > deadline {
            return (status, v);
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

fn names(list: &Value) -> Vec<String> {
    list["sessions"]
        .as_array()
        .unwrap_or(&Vec::new())
        .iter()
        .map(|s| s["session"].as_str().unwrap_or_default().to_string())
        .collect()
}

#[tokio::test(flavor = "multi_thread")]
async fn a_rogue_peer_without_the_secret_gets_no_session_no_request_and_no_token() {
    let dir = common::temp_dir("fleet-trust");
    let tokens = dir.join("tokens");
    std::fs::write(&tokens, format!("alice {ALICE}\nbob {BOB}\n")).unwrap();
    let tokens = tokens.display().to_string();
    let fleet = Fleet::start(2, &["--tokens-file", &tokens]);
    // The rogue: an HTTP server of its own, and a zenoh peer of the first instance.
    let http = RogueHttp::start();
    let rogue_zenoh = zenoh_peer(&fleet.instance(0).zenoh).await;
    let rogue = RoguePeer::join(&rogue_zenoh, &http.url).await;
    let observer = zenoh_peer(&fleet.instance(1).zenoh).await;
    fleet.wait_settled(&observer).await;
    // Past the time the instances take to ask a newcomer for its info, twice over.
    tokio::time::sleep(Duration::from_secs(3)).await;

    let c = client();
    for i in 0..9 {
        let via = fleet.instance(i % 2);
        let (status, v) = send(
            &c,
            reqwest::Method::POST,
            &via.url("/v1/sessions"),
            ALICE,
            Some(json!({"session": format!("trust-{i}"), "kind": "pose_graph_2d"})),
        )
        .await;
        assert_eq!(status, 201, "create trust-{i}: {v}\n{}", fleet.logs());
    }
    for (token, expected) in [(ALICE, 9), (BOB, 0)] {
        for i in 0..2 {
            let (status, list) = send(
                &c,
                reqwest::Method::GET,
                &fleet.instance(i).url("/v1/sessions"),
                token,
                None,
            )
            .await;
            assert_eq!(status, 200, "{list}");
            let listed = names(&list);
            assert!(!listed.contains(&"rogue-session".to_string()), "{list}");
            assert_eq!(listed.len(), expected, "{list}");
        }
    }
    // Every session is held by a real instance, and readable through either.
    for i in 0..9 {
        let url = fleet
            .instance((i + 1) % 2)
            .url(&format!("/v1/sessions/trust-{i}/estimate"));
        let (status, v) = send(&c, reqwest::Method::GET, &url, ALICE, None).await;
        assert_eq!(status, 200, "{v}");
        assert_ne!(v["sequence"], 424242, "{v}");
    }
    // Over zenoh: the gateway is a real instance; the lists hold no rogue session.
    let listed = rpc(&observer, &json!({"op": "list_sessions"})).await;
    assert!(
        !names(&listed).contains(&"rogue-session".to_string()),
        "{listed}"
    );
    let real: Vec<Value> = infos(&observer)
        .await
        .into_iter()
        .filter(|i| i["instance"] != "0rogue")
        .collect();
    assert_eq!(real.len(), 2, "{real:?}");
    for info in &real {
        let live = info["live"].as_object().unwrap();
        assert!(!live.contains_key("0rogue"), "{info}");
    }
    let gateways: Vec<&Value> = real.iter().filter(|i| i["rpc_gateway"] == true).collect();
    assert_eq!(gateways.len(), 1, "{real:?}");

    assert!(
        http.requests().is_empty(),
        "the rogue received {:?}",
        http.requests()
    );
    assert_eq!(rogue.forwarded.load(Ordering::SeqCst), 0);
    assert!(
        fleet.logs().contains("valid fleet proof"),
        "the operator is told: {}",
        fleet.logs()
    );

    // An assertion of another tenant, forged without the secret, is refused.
    let forged = c
        .get(fleet.instance(0).url("/v1/sessions/trust-0/estimate"))
        .header("factord-forwarded-by", "0rogue")
        .header(
            "factord-forwarded-caller",
            format!("principal:{}", hex_of("alice")),
        )
        .header("factord-forwarded-proof", "1700000000.00112233.deadbeef")
        .send()
        .await
        .unwrap();
    assert_eq!(forged.status().as_u16(), 401);
    let v: Value = forged.json().await.unwrap();
    assert_eq!(v["error"]["code"], "fleet_proof_invalid", "{v}");
}

/// The first successful answer to `command` on `factord/rpc`.
async fn rpc(z: &zenoh::Session, command: &Value) -> Value {
    let replies = z
        .get("factord/rpc")
        .payload(command.to_string())
        .timeout(Duration::from_secs(10))
        .await
        .unwrap();
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result() {
            return serde_json::from_slice(&sample.payload().to_bytes()).unwrap();
        }
    }
    panic!("no answer to {command}");
}

fn hex_of(text: &str) -> String {
    text.bytes().map(|b| format!("{b:02x}")).collect()
}

/// `factord serve --fleet` with the given extra flags; returns its exit status (or `None` if it
/// still runs after `within`, then killed) and its stderr.
fn serve_briefly(dir: &std::path::Path, extra: &[&str], within: Duration) -> (Option<i32>, String) {
    let log = dir.join("serve.stderr");
    let mut child = Command::new(env!("CARGO_BIN_EXE_factord"))
        .arg("serve")
        .args([
            "--fleet",
            "--instance-id",
            "lone",
            "--listen",
            "127.0.0.1:0",
        ])
        .args(["--zenoh-listen", &format!("tcp/127.0.0.1:{}", free_port())])
        .args(["--zenoh-multicast", "off", "--state-dir"])
        .arg(dir.join("state"))
        .args(extra)
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + within;
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status.code();
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    (status, std::fs::read_to_string(&log).unwrap_or_default())
}

#[test]
fn a_fleet_without_a_secret_refuses_to_start_unless_its_network_is_declared_trusted() {
    let dir = common::temp_dir("fleet-no-secret");
    let (status, log) = serve_briefly(&dir, &[], Duration::from_secs(20));
    assert!(
        matches!(status, Some(code) if code != 0),
        "{status:?}: {log}"
    );
    assert!(log.contains("--fleet-secret-file"), "{log}");
    assert!(log.contains("--fleet-trusted-network"), "{log}");

    let short = dir.join("short-secret");
    std::fs::write(&short, "too short").unwrap();
    let short = short.display().to_string();
    let (status, log) = serve_briefly(
        &dir,
        &["--fleet-secret-file", &short],
        Duration::from_secs(20),
    );
    assert!(
        matches!(status, Some(code) if code != 0),
        "{status:?}: {log}"
    );
    assert!(log.contains("at least 32 are needed"), "{log}");

    let (status, log) = serve_briefly(&dir, &["--fleet-trusted-network"], Duration::from_secs(3));
    assert_eq!(status, None, "it runs: {log}");
    assert!(log.contains("no secret (--fleet-trusted-network)"), "{log}");
}
