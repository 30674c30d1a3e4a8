//! A robot that subscribes to its own keys while the session is idle (issue 54 item 4): it
//! receives its whole trajectory and its `map_from_odom` at once, with no solve and no query
//! first. The server declared the robot's keys when its first pose appeared, before anyone
//! subscribed; zenoh then tells it of the subscriber (through a router, a moment after the
//! subscription), and the server serves that new audience. Then the robot leaves and comes
//! back on its binary key alone: served whole again. Both topologies a robot can use.

use crate::common;
use crate::robot_streams::{
    connect, robots_session, same, samples, values, Samples, Topology, View,
};

use std::time::{Duration, Instant};

use common::server::{get, post};
use common::square_walk::{closure, robot_batch, truth};
use serde_json::{json, Value};

const SESSION: &str = "late";

/// Reads `rx` into `view` until `done` holds, or panics after 20 s naming `what`.
fn wait_for(rx: &Samples, base: &str, view: &mut View, what: &str, done: impl Fn(&View) -> bool) {
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        view.take(rx, base);
        if done(view) {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "{what} not received in 20 s: {}",
            view.summary()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

async fn a_late_robot_is_served_whole(topology: Topology) {
    let (_router, s, z) = connect(topology).await;
    let c = robots_session(&s, SESSION).await;
    let url = |path: &str| s.url(&format!("/v1/sessions/{SESSION}{path}"));
    let (a, b) = (truth(0, 40), truth(13, 30));
    for body in [
        robot_batch('a', &a, 0..30),
        robot_batch('b', &b, 0..20),
        json!({"factors": [closure(&a, 18, &b, 5), closure(&a, 22, &b, 9), closure(&a, 26, &b, 13)]}),
    ] {
        let (status, v) = post(&c, &url("/batches"), &body).await;
        assert_eq!(status, 200, "{v}");
    }
    let (status, v) = post(&c, &url("/optimize?wait=true"), &json!({})).await;
    assert_eq!(status, 200, "{v}");
    let (_, b_map) = get(&c, &url("/estimate?robot=b")).await;
    let (_, b_odom) = get(&c, &url("/estimate?robot=b&frame=odom")).await;
    let (_, report) = get(&c, &url("/robots")).await;
    let b_frame: Value = report["robots"]
        .as_array()
        .unwrap()
        .iter()
        .find(|r| r["robot"] == "b")
        .map(|r| r["map_from_odom"].clone())
        .unwrap();
    let (want_map, want_odom) = (values(&b_map), values(&b_odom));
    assert_eq!(want_map.len(), 20);

    // Idle from here on: nothing is posted while robot b subscribes.
    let base = format!("factord/{SESSION}/robot/b/");
    let (sub, rx) = samples(&z, &format!("{base}**")).await;
    let mut view = View::default();
    wait_for(&rx, &base, &mut view, "b's whole view", |view| {
        view.frames.last().map(|f| &f["map_from_odom"]) == Some(&b_frame)
            && ["poses", "bin/poses"].iter().all(|k| {
                view.latest
                    .get(*k)
                    .is_some_and(|got| same(got, &want_map, 1e-9))
            })
            && ["odom_poses", "bin/odom_poses"].iter().all(|k| {
                view.latest
                    .get(*k)
                    .is_some_and(|got| same(got, &want_odom, 1e-9))
            })
    });

    // The robot leaves, then comes back on one key: its audience is new, so it is served whole
    // again (the server cannot tell who subscribes, only that somebody does again).
    drop(sub);
    // Time for zenoh to tell the server the key lost its audience (loopback: milliseconds).
    tokio::time::sleep(Duration::from_secs(1)).await;
    let key = format!("{base}bin/poses");
    let (_sub, rx) = samples(&z, &key).await;
    let mut view = View::default();
    wait_for(&rx, &base, &mut view, "b's whole view again", |view| {
        view.latest
            .get("bin/poses")
            .is_some_and(|got| same(got, &want_map, 1e-9))
    });
    let (_, after) = get(&c, &url("/robots")).await;
    assert_eq!(after, report, "nothing changed the session meanwhile");
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn a_late_robot_is_served_whole_as_a_peer() {
    a_late_robot_is_served_whole(Topology::Peer).await;
}

#[tokio::test(flavor = "multi_thread")]
async fn a_late_robot_is_served_whole_through_a_router() {
    a_late_robot_is_served_whole(Topology::Router).await;
}
