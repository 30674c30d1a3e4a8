//! ROS 2 over rmw_zenoh (issue 19): a robot written in Python publishes real CDR messages the
//! way rmw_zenoh_cpp does (key expressions, attachment, liveliness tokens) to a real `factord
//! serve` process bound to its topics, and reads the optimised path and pose back with the
//! same tools (`tests/ros2/robot_odometry.py`).
//!
//! The venv `~/.cache/factord/venvs/ros2` holds rosbags (CDR and the Jazzy type store),
//! eclipse-zenoh (the client's version), numpy and xxhash; it is made once (PyPI must be
//! reachable). Without Python or PyPI the test skips with the reason, except under `CI=true`.

use crate::common;

use std::path::PathBuf;
use std::time::Duration;

use common::server::{
    client, create, delete_session, holders, ros_nodes_until, zenoh_peer, TestServer,
};
use serde_json::json;

pub(crate) fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The ROS 2 tests' Python (rosbags, zenoh), or `None` after saying why it is missing.
pub(crate) fn python() -> Option<PathBuf> {
    let installs = [vec![
        "rosbags==0.11.9".into(),
        "eclipse-zenoh==1.10.2".into(),
        "numpy".into(),
        "xxhash".into(),
    ]];
    match common::python_venv("ros2", &installs) {
        Ok(python) => Some(python),
        Err(reason) => common::skip_or_fail(&format!("no Python environment for ROS 2: {reason}")),
    }
}

#[test]
fn a_ros2_robot_over_rmw_zenoh_feeds_a_session_and_reads_its_path() {
    let Some(python) = python() else { return };
    let server = TestServer::start(&[]);
    common::run_python_script(&python, &server, "tests/ros2/robot_odometry.py", &[]);
}

/// Issue 56: a SLAM front-end's loop closures and landmark sightings (`factord_msgs`) over
/// rmw_zenoh close a drifted square and map its landmarks (`tests/ros2/robot_slam.py`).
#[test]
fn a_slam_robot_over_rmw_zenoh_closes_a_loop_and_maps_landmarks() {
    let Some(python) = python() else { return };
    let server = TestServer::start(&[]);
    common::run_python_script(&python, &server, "tests/ros2/robot_slam.py", &[]);
}

/// Two robots in their own namespaces and odometry frames, a node each, merged into one map by
/// closures between them (`tests/ros2/robot_fleet.py`): the robots a zenoh peer of factord.
#[test]
fn two_robots_get_a_node_each_and_merge_into_one_map_over_rmw_zenoh() {
    let Some(python) = python() else { return };
    let server = TestServer::start(&[]);
    common::run_python_script(&python, &server, "tests/ros2/robot_fleet.py", &[]);
}

/// The same through a zenoh router, as rmw_zenoh deploys it: factord and the robots (zenoh
/// clients, as rmw_zenoh's nodes are) connect to the router only.
#[test]
fn two_robots_get_a_node_each_through_a_zenoh_router() {
    let Some(python) = python() else { return };
    let runtime = tokio::runtime::Runtime::new().expect("a runtime");
    let endpoint = format!("tcp/127.0.0.1:{}", common::server::free_port());
    let _router = runtime.block_on(common::server::zenoh_session("router", "listen", &endpoint));
    let server = TestServer::start(&["--zenoh-connect", &endpoint]);
    let args = ["--router", endpoint.as_str()];
    common::run_python_script(&python, &server, "tests/ros2/robot_fleet.py", &args);
}

#[test]
fn a_ros2_robot_with_an_imu_feeds_a_sliding_window() {
    let Some(python) = python() else { return };
    let server = TestServer::start(&[]);
    common::run_python_script(&python, &server, "tests/ros2/robot_imu.py", &[]);
}

/// A ROS 2 bag (MCAP, written by rosbags from sphere2500's first 300 poses) replayed into a
/// session as `ros2 bag play` over rmw_zenoh would: the recorded CDR bytes, unchanged.
#[test]
fn a_ros2_bag_replayed_over_rmw_zenoh_becomes_the_sessions_path() {
    let Some(python) = python() else { return };
    let data = std::env::var_os("FACTORD_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| repo().join("../shared/data"));
    let g2o = data.join("3d/sesync/sphere2500.g2o");
    if !g2o.exists() {
        common::skip_or_fail::<()>(&format!("no dataset at {}", g2o.display()));
        return;
    }
    let server = TestServer::start(&[]);
    let g2o = g2o.to_str().expect("a utf-8 path");
    common::run_python_script(
        &python,
        &server,
        "tests/ros2/bag_replay.py",
        &["--g2o", g2o],
    );
}

/// A binding lives as long as its session here: deleted, its node leaves the ROS graph (the
/// binding must not keep the session alive, nor feed a session that is gone).
#[tokio::test(flavor = "multi_thread")]
async fn a_deleted_sessions_node_leaves_the_ros_graph() {
    let server = TestServer::start(&[]);
    let c = client();
    let session = json!({"session": "gone", "kind": "pose_graph_3d",
                         "ros2": {"domain_id": 3, "odometry_topic": "/odom", "path_topic": "/path"}});
    create(&c, &server, &session).await;
    let z = zenoh_peer(&server.zenoh).await;
    let within = Duration::from_secs(10);
    let ours = |nodes: &[(String, String)]| !holders(nodes, "factord_gone").is_empty();
    assert!(
        ours(&ros_nodes_until(&z, 3, within, ours).await),
        "the node joins"
    );
    let (status, v) = delete_session(&c, &server, "gone").await;
    assert!((200..300).contains(&status), "{status}: {v}");
    let left = ros_nodes_until(&z, 3, within, |nodes| !ours(nodes)).await;
    assert!(
        !ours(&left),
        "the deleted session's node is still in the ROS graph: {left:?}"
    );
    server.assert_no_panic();
}
