//! Deleting and creating durable sessions against the real binary: a deletion the disk refuses
//! is an error (the session stays), a deletion acknowledged survives `kill -9`, a tombstone left
//! by a crash is finished at start, a directory on disk is never overwritten by a creation (and
//! counts against `max_sessions`), and a creation refused part way leaves no directory behind.

use crate::common;

use std::path::Path;
use std::time::{Duration, Instant};

use common::server::{client, create, delete_session, get, post, recovered, TestServer};
use serde_json::{json, Value};

fn request(name: &str) -> Value {
    json!({"session": name, "kind": "pose_graph_2d", "auto_optimize": {"policy": "manual"}})
}

/// Creates `name` with `n` one-pose batches.
async fn create_with_batches(c: &reqwest::Client, s: &TestServer, name: &str, n: u64) {
    create(c, s, &request(name)).await;
    let url = s.url(&format!("/v1/sessions/{name}/batches"));
    for key in 0..n {
        let batch = json!({"variables": [{"key": key, "kind": "se2", "value": [key, 0, 0]}]});
        assert_eq!(post(c, &url, &batch).await.0, 200);
    }
}

/// What `sessions/` holds, by name.
fn on_disk(state: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(state.join("sessions"))
        .map(|d| {
            d.map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    names.sort();
    names
}

async fn listed(c: &reqwest::Client, s: &TestServer) -> Vec<String> {
    let (_, v) = get(c, &s.url("/v1/sessions")).await;
    v["sessions"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["session"].as_str().unwrap().to_string())
        .collect()
}

/// The disk refuses the deletion (`sessions/` is replaced by a file, so its directory cannot be
/// moved aside): DELETE is 503 `delete_failed` and the session stays, in memory and on disk.
/// Once the disk works, DELETE is 200 and a `kill -9` right after it does not bring it back.
#[tokio::test(flavor = "multi_thread")]
async fn a_delete_the_disk_refuses_is_an_error_and_an_acknowledged_one_survives_kill_9() {
    let state = common::temp_dir("delete-refused");
    let c = client();
    let s = TestServer::start_at(&state, &["--no-zenoh"], &[]);
    create_with_batches(&c, &s, "kept", 3).await;
    let sessions = state.join("sessions");
    let moved = state.join("sessions.moved");
    std::fs::rename(&sessions, &moved).unwrap();
    std::fs::write(&sessions, b"not a directory").unwrap();
    let (status, v) = delete_session(&c, &s, "kept").await;
    assert_eq!(
        (status, v["error"]["code"].as_str()),
        (503, Some("delete_failed")),
        "{v}"
    );
    assert_eq!(v["error"]["retry_after"], 5, "{v}");
    std::fs::remove_file(&sessions).unwrap();
    std::fs::rename(&moved, &sessions).unwrap();
    let (status, stats) = get(&c, &s.url("/v1/sessions/kept")).await;
    assert_eq!((status, &stats["sequence"]), (200, &json!(3)), "{stats}");
    // Still writable: the journal was not closed by the refused deletion.
    let batch = json!({"variables": [{"key": 3, "kind": "se2", "value": [3, 0, 0]}]});
    assert_eq!(
        post(&c, &s.url("/v1/sessions/kept/batches"), &batch)
            .await
            .0,
        200
    );
    s.kill();

    let s = TestServer::start_at(&state, &["--no-zenoh"], &[]);
    let (stats, _) = recovered(&c, &s, "kept", Instant::now()).await;
    assert_eq!(
        stats["sequence"], 4,
        "the refused deletion lost nothing: {stats}"
    );
    assert_eq!(delete_session(&c, &s, "kept").await.0, 200);
    s.kill();
    let s = TestServer::start_at(&state, &["--no-zenoh"], &[]);
    assert_eq!(get(&c, &s.url("/v1/sessions/kept")).await.0, 404);
    assert_eq!(on_disk(&state), Vec::<String>::new());
    s.assert_no_panic();
}

/// A crash between the tombstone's rename and its removal leaves the tombstone (here made by
/// hand, as the server names it): the next start removes it and does not list it.
#[tokio::test(flavor = "multi_thread")]
async fn a_tombstone_left_by_a_crash_is_finished_at_start() {
    let state = common::temp_dir("delete-tombstone");
    let c = client();
    let s = TestServer::start_at(&state, &["--no-zenoh"], &[]);
    create_with_batches(&c, &s, "gone", 2).await;
    create_with_batches(&c, &s, "stays", 2).await;
    s.kill();
    let sessions = state.join("sessions");
    std::fs::rename(sessions.join("gone"), sessions.join(".deleted-gone-1")).unwrap();

    let s = TestServer::start_at(&state, &["--no-zenoh"], &[]);
    recovered(&c, &s, "stays", Instant::now()).await;
    assert_eq!(listed(&c, &s).await, vec!["stays".to_string()]);
    assert_eq!(get(&c, &s.url("/v1/sessions/gone")).await.0, 404);
    assert_eq!(on_disk(&state), vec!["stays".to_string()]);
    // The name is free again.
    create(&c, &s, &request("gone")).await;
    s.assert_no_panic();
}

/// A session whose `session.json` cannot be read is not loaded, and its name cannot be created
/// again (409 `session_on_disk`, with a log line): its journal is kept byte for byte. Its
/// directory counts against `max_sessions`.
#[tokio::test(flavor = "multi_thread")]
async fn a_directory_on_disk_is_never_overwritten_and_counts_against_max_sessions() {
    let state = common::temp_dir("create-on-disk");
    let config = state.with_extension("json");
    std::fs::write(&config, json!({"limits": {"max_sessions": 2}}).to_string()).unwrap();
    let extra = ["--no-zenoh", "--config", config.to_str().unwrap()];
    let c = client();
    let s = TestServer::start_at(&state, &extra, &[]);
    create_with_batches(&c, &s, "broken", 5).await;
    create_with_batches(&c, &s, "fine", 1).await;
    s.kill();
    let dir = state.join("sessions/broken");
    std::fs::write(dir.join("session.json"), b"{ garbage").unwrap();
    let journal = std::fs::read(dir.join("journal.log")).unwrap();
    assert!(!journal.is_empty());

    let s = TestServer::start_at(&state, &extra, &[]);
    recovered(&c, &s, "fine", Instant::now()).await;
    assert_eq!(get(&c, &s.url("/v1/sessions/broken")).await.0, 404);
    let (status, v) = post(&c, &s.url("/v1/sessions"), &request("broken")).await;
    assert_eq!(
        (status, v["error"]["code"].as_str()),
        (409, Some("session_on_disk")),
        "{v}"
    );
    assert_eq!(std::fs::read(dir.join("journal.log")).unwrap(), journal);
    assert_eq!(
        std::fs::read(dir.join("session.json")).unwrap(),
        b"{ garbage"
    );
    assert!(s.stderr().contains("creation refused"), "{}", s.stderr());
    // "fine" is loaded and "broken" is on disk: the cap of 2 is reached.
    let (status, v) = post(&c, &s.url("/v1/sessions"), &request("third")).await;
    assert_eq!(
        (status, v["error"]["code"].as_str()),
        (503, Some("too_many_sessions")),
        "{v}"
    );
    assert_eq!(
        on_disk(&state),
        vec!["broken".to_string(), "fine".to_string()]
    );
    s.assert_no_panic();
}

/// The lowest file descriptor the process does not use.
fn lowest_free_fd(pid: u32) -> u64 {
    let used: std::collections::HashSet<u64> = std::fs::read_dir(format!("/proc/{pid}/fd"))
        .unwrap()
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse().ok())
        .collect();
    (0..).find(|fd| !used.contains(fd)).unwrap()
}

fn set_fd_limit(pid: u32, soft: &str) {
    let status = std::process::Command::new("prlimit")
        .arg(format!("--pid={pid}"))
        .arg(format!("--nofile={soft}:"))
        .status()
        .expect("prlimit runs");
    assert!(status.success());
}

/// The server runs out of file descriptors (its limit lowered, as under load): the directory
/// is made (that needs none) but its files cannot be, so the creation is refused with 503
/// `journal_failed` and leaves no directory behind, and nothing comes back after a restart.
#[tokio::test(flavor = "multi_thread")]
async fn a_creation_refused_part_way_leaves_no_directory() {
    if std::process::Command::new("prlimit")
        .arg("--version")
        .output()
        .is_err()
    {
        return common::skip_or_fail("prlimit (util-linux) is not installed").unwrap_or(());
    }
    let state = common::temp_dir("create-rollback");
    let c = client();
    let s = TestServer::start_at(&state, &["--no-zenoh"], &[]);
    create(&c, &s, &request("first")).await; // also opens the connection used below
    let original = std::fs::read_to_string(format!("/proc/{}/limits", s.pid())).unwrap();
    let soft = original
        .lines()
        .find(|l| l.starts_with("Max open files"))
        .and_then(|l| l.split_whitespace().nth(3))
        .unwrap()
        .to_string();
    set_fd_limit(s.pid(), &lowest_free_fd(s.pid()).to_string());
    let (status, v) = post(&c, &s.url("/v1/sessions"), &request("nofd")).await;
    set_fd_limit(s.pid(), &soft);
    assert_eq!(
        (status, v["error"]["code"].as_str()),
        (503, Some("journal_failed")),
        "{v}"
    );
    assert_eq!(on_disk(&state), vec!["first".to_string()], "{v}");
    assert_eq!(get(&c, &s.url("/v1/sessions/nofd")).await.0, 404);
    s.kill();
    let s = TestServer::start_at(&state, &["--no-zenoh"], &[]);
    let deadline = Instant::now() + Duration::from_secs(10);
    while listed(&c, &s).await.is_empty() {
        assert!(Instant::now() < deadline);
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    assert_eq!(listed(&c, &s).await, vec!["first".to_string()]);
    // The name was never taken.
    create(&c, &s, &request("nofd")).await;
    s.assert_no_panic();
}
