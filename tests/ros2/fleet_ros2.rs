//! A ROS 2 binding in a fleet follows its session: the owner's node is in the ROS graph; after
//! a `kill -9` of the owner, the instance that adopts the session joins the graph with it; when
//! the owner comes back and the session moves home, the interim instance's node leaves. At every
//! settled point exactly one node speaks for the session (two would feed it twice).

use crate::common;

use std::time::Duration;

use common::fleet::Fleet;
use common::server::{client, holders, post, ros_nodes_until, zenoh_peer};
use serde_json::json;

const NODE: &str = "factord_rosbot";
const DOMAIN: u32 = 5;

#[tokio::test(flavor = "multi_thread")]
async fn a_ros2_binding_follows_its_session_through_the_fleet() {
    let mut fleet = Fleet::start(2, &[]);
    let owner = fleet.owner("rosbot");
    let other = 1 - owner;
    // Watched through the instance that stays up.
    let z = zenoh_peer(&fleet.instance(other).zenoh).await;
    fleet.wait_settled(&z).await;
    let create = json!({"session": "rosbot", "kind": "pose_graph_3d",
                        "ros2": {"domain_id": DOMAIN, "odometry_topic": "/odom"}});
    let (status, v) = post(
        &client(),
        &fleet.instance(other).url("/v1/sessions"),
        &create,
    )
    .await;
    assert_eq!(status, 201, "{v}\n{}", fleet.logs());

    let within = Duration::from_secs(40);
    let one = |nodes: &[(String, String)]| holders(nodes, NODE).len() == 1;
    let nodes = ros_nodes_until(&z, DOMAIN, within, one).await;
    let first = holders(&nodes, NODE);
    assert_eq!(first.len(), 1, "{nodes:?}\n{}", fleet.logs());

    // The owner dies: the other instance adopts the session, and its binding with it.
    fleet.kill(owner);
    let moved = |nodes: &[(String, String)]| {
        let h = holders(nodes, NODE);
        h.len() == 1 && h != first
    };
    let nodes = ros_nodes_until(&z, DOMAIN, within, moved).await;
    assert!(moved(&nodes), "after the kill: {nodes:?}\n{}", fleet.logs());
    let interim = holders(&nodes, NODE);

    // The owner is back: the session moves home, the interim node leaves.
    fleet.start_instance(owner);
    fleet.wait_settled(&z).await;
    let home = |nodes: &[(String, String)]| {
        let h = holders(nodes, NODE);
        h.len() == 1 && h != interim
    };
    let nodes = ros_nodes_until(&z, DOMAIN, within, home).await;
    assert!(
        home(&nodes),
        "after the move home: {nodes:?}\n{}",
        fleet.logs()
    );
}
