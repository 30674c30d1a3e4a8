//! One server per state directory, enforced by an OS lock: two servers started at once on one
//! directory never both serve (the second exits non-zero naming the directory and the holder),
//! and a lock file left by a killed server does not block the next start, whatever pid it holds.

use crate::common;

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::server::{client, get, TestServer};

/// A server process, killed when dropped: a failing assertion must not leave it running (it
/// would hold its state directory's lock, and a port, after the test run).
struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// `factord serve` on `state`, HTTP on a free port, no zenoh; stderr to `log`.
fn spawn(state: &Path, log: &Path) -> Server {
    let child = Command::new(env!("CARGO_BIN_EXE_factord"))
        .args([
            "serve",
            "--listen",
            "127.0.0.1:0",
            "--no-zenoh",
            "--state-dir",
        ])
        .arg(state)
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(log).unwrap())
        .spawn()
        .expect("factord starts");
    Server(child)
}

#[tokio::test(flavor = "multi_thread")]
async fn two_servers_started_at_once_on_one_state_directory_never_both_serve() {
    const ROUNDS: usize = 20;
    let state = common::temp_dir("lock-race");
    let c = client();
    for round in 0..ROUNDS {
        let _ = std::fs::remove_file(state.join("server.json"));
        let logs = [0, 1].map(|i| state.with_extension(format!("{round}-{i}.log")));
        let mut children = [spawn(&state, &logs[0]), spawn(&state, &logs[1])];
        // The loser exits at once (the lock is the first thing a server takes).
        let deadline = Instant::now() + Duration::from_secs(15);
        let (loser, status) = loop {
            if let Some((i, status)) = children
                .iter_mut()
                .enumerate()
                .find_map(|(i, c)| Some((i, c.0.try_wait().unwrap()?)))
            {
                break (i, status);
            }
            assert!(
                Instant::now() < deadline,
                "round {round}: both servers still run: {}\n---\n{}",
                std::fs::read_to_string(&logs[0]).unwrap(),
                std::fs::read_to_string(&logs[1]).unwrap()
            );
            std::thread::sleep(Duration::from_millis(10));
        };
        let winner = 1 - loser;
        let log = std::fs::read_to_string(&logs[loser]).unwrap();
        assert!(
            !status.success(),
            "round {round}: the loser exited 0: {log}"
        );
        // The winner serves, with its own pid in server.json and its address answering.
        let info = loop {
            let text = std::fs::read_to_string(state.join("server.json")).unwrap_or_default();
            if let Ok(v) = serde_json::from_str::<serde_json::Value>(&text) {
                break v;
            }
            assert!(
                children[winner].0.try_wait().unwrap().is_none(),
                "round {round}: the winner exited too: {}",
                std::fs::read_to_string(&logs[winner]).unwrap()
            );
            assert!(Instant::now() < deadline, "round {round}: no server.json");
            std::thread::sleep(Duration::from_millis(10));
        };
        let winner_pid = children[winner].0.id();
        assert_eq!(info["pid"], winner_pid, "round {round}");
        let expected = format!(
            "state directory {}: in use by process {winner_pid}",
            state.display()
        );
        assert!(
            log.contains(&expected) || log.contains("in use by another process"),
            "round {round}: {log}"
        );
        let health = format!("http://{}/v1/health", info["http"].as_str().unwrap());
        assert_eq!(get(&c, &health).await.0, 200, "round {round}");
        // A crash of the winner releases the lock: the next round starts from there.
        children[winner].0.kill().unwrap();
        children[winner].0.wait().unwrap();
    }
}

/// A server killed with `kill -9` leaves `factord.lock` with its pid. When the system gives
/// that pid to another process (here: this test), the next start must not take it for a
/// running server: only the OS lock counts. A second server then exits naming the first.
#[tokio::test(flavor = "multi_thread")]
async fn a_lock_file_naming_a_live_process_does_not_block_a_start() {
    let state = common::temp_dir("lock-stale");
    std::fs::write(state.join("factord.lock"), std::process::id().to_string()).unwrap();
    let s = TestServer::start_at(&state, &["--no-zenoh"], &[]);
    assert_eq!(get(&client(), &s.url("/v1/health")).await.0, 200);
    let log = state.with_extension("second.log");
    let status = spawn(&state, &log).0.wait().unwrap();
    let message = std::fs::read_to_string(&log).unwrap();
    assert!(!status.success(), "{message}");
    assert!(
        message.contains(&format!(
            "state directory {}: in use by process {}",
            state.display(),
            s.pid()
        )),
        "{message}"
    );
    s.assert_no_panic();
}
