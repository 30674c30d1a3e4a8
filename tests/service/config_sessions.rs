//! Sessions the config file asks for (`"sessions": [...]`): created at start as a client's
//! creation would be (a ROS 2 binding included, which then joins the ROS graph with no client;
//! the config's server-wide factor types included), left as they are when they exist (after a
//! kill -9 the recovered session keeps what it was sent), and a bad request stops the start
//! naming its field.

use crate::common;

use std::path::Path;
use std::time::{Duration, Instant};

use common::cli::factord;
use common::server::{get, holders, post, ros_nodes_until, zenoh_peer, TestServer};
use common::user_between_se2;
use serde_json::{json, Value};

fn write_config(path: &Path, config: Value) -> String {
    std::fs::write(path, config.to_string()).unwrap();
    path.display().to_string()
}

/// Whether factord's ROS node for `robot1` is in the ROS graph (domain 0).
async fn robot1_in_ros_graph(zenoh_endpoint: &str) -> bool {
    let z = zenoh_peer(zenoh_endpoint).await;
    let has = |nodes: &[(String, String)]| !holders(nodes, "factord_robot1").is_empty();
    has(&ros_nodes_until(&z, 0, Duration::from_secs(10), has).await)
}

#[tokio::test(flavor = "multi_thread")]
async fn configured_sessions_are_created_once_and_kept() {
    let dir = common::temp_dir("config-sessions");
    let config = write_config(
        &dir.join("factord.json"),
        json!({
            "factor_types": [user_between_se2()],
            "sessions": [
                {"session": "robot1", "kind": "pose_graph_3d",
                 "ros2": {"odometry_topic": "/odom", "path_topic": "/path"}},
                {"session": "plane", "kind": "pose_graph_2d"}
            ]
        }),
    );
    let state = dir.join("state");
    let s = TestServer::start_at(&state, &["--config", &config], &[]);
    let c = reqwest::Client::new();
    let (_, list) = get(&c, &s.url("/v1/sessions")).await;
    let mut names: Vec<&str> = list["sessions"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["session"].as_str().unwrap())
        .collect();
    names.sort();
    assert_eq!(names, ["plane", "robot1"], "{list}");
    let (_, plane) = get(&c, &s.url("/v1/sessions/plane")).await;
    assert_eq!(
        plane["factor_types"],
        json!(["user_between_se2"]),
        "the server-wide factor types, as a client's session gets them: {plane}"
    );
    assert!(
        robot1_in_ros_graph(&s.zenoh).await,
        "the configured binding is not in the ROS graph"
    );

    // What the session is sent survives a kill -9 and a start with the same config.
    let batch = json!({"variables": [{"key": 0, "kind": "se2", "value": [1, 2, 0], "fixed": true},
                                     {"key": 1, "kind": "se2", "value": [2, 2, 0]}],
                       "factors": [{"type": "between_se2", "keys": [0, 1],
                                    "measurement": [1, 0, 0], "sigmas": [0.1, 0.1, 0.1]}]});
    let (status, v) = post(&c, &s.url("/v1/sessions/plane/batches?wait=true"), &batch).await;
    assert_eq!(status, 200, "{v}");
    s.kill();
    let s = TestServer::start_at(&state, &["--config", &config], &[]);
    let deadline = Instant::now() + Duration::from_secs(20);
    let stats = loop {
        let (_, stats) = get(&c, &s.url("/v1/sessions/plane")).await;
        if stats["num_variables"] == 2 || Instant::now() > deadline {
            break stats;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    assert_eq!(
        stats["num_variables"], 2,
        "the recovered session, not a new one: {stats}"
    );
    assert!(
        robot1_in_ros_graph(&s.zenoh).await,
        "the binding after the restart"
    );
    assert!(s.stderr().contains("created from the config"));
    s.assert_no_panic();
}

#[test]
fn a_bad_configured_session_stops_the_start_naming_its_field() {
    let dir = common::temp_dir("config-sessions-bad");
    let cases = [
        (
            json!([{"session": "r", "kind": "pose_graph_3d",
                    "ros2": {"odometry_topic": "/odom", "imu_topic": "/imu"}}]),
            "sessions[0].ros2.imu_topic",
        ),
        (
            json!([{"session": "ok", "kind": "pose_graph_2d"}, {"kind": "pose_graph_2d"}]),
            "sessions[1].session",
        ),
        (
            json!([{"session": "x", "kind": "nope"}]),
            "sessions[0].kind",
        ),
    ];
    for (i, (sessions, field)) in cases.into_iter().enumerate() {
        let config = write_config(
            &dir.join(format!("bad{i}.json")),
            json!({ "sessions": sessions }),
        );
        let out = factord()
            .args(["serve", "--no-zenoh", "--listen", "127.0.0.1:0", "--config"])
            .arg(&config)
            .arg("--state-dir")
            .arg(dir.join(format!("state{i}")))
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{stderr}");
        assert!(stderr.contains(field), "{field}: {stderr}");
    }
}

#[test]
fn a_session_named_twice_in_the_config_stops_the_start() {
    let dir = common::temp_dir("config-sessions-twice");
    let config = write_config(
        &dir.join("twice.json"),
        json!({"sessions": [{"session": "a", "kind": "pose_graph_2d"},
                            {"session": "b", "kind": "pose_graph_2d"},
                            {"session": "a", "kind": "pose_graph_3d"}]}),
    );
    let out = factord()
        .args([
            "serve",
            "--no-zenoh",
            "--listen",
            "127.0.0.1:0",
            "--config",
            &config,
        ])
        .arg("--state-dir")
        .arg(dir.join("state"))
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(stderr.contains("sessions[2].session"), "{stderr}");
    assert!(stderr.contains("sessions[0]"), "{stderr}");
    assert!(
        !dir.join("state/sessions/a").exists(),
        "nothing is created before the refusal"
    );
}
