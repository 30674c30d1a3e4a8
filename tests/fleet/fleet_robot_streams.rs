//! A robot's own zenoh keys follow its session's owner (issue 54 item 4): two robots in a
//! session of a two-instance fleet merge, each reads its trajectory on
//! `factord/<s>/robot/<id>/…`; the owner is killed (-9), the survivor adopts the session from
//! the journal, and the same subscriptions (never declared again) receive the robot's later
//! poses from the adopter, whose `robot/<id>/estimate` queryable answers as `get_estimate`.

use crate::common;

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use common::fleet::Fleet;
use common::server::{json_samples, zenoh_get};
use common::square_walk::{closure, robot_batch, sent, truth};
use factord::api::robots::{robot_key, robot_of_key};
use factord::geometry::Se2;
use serde_json::{json, Value};

const SESSION: &str = "robots-follow";

/// A zenoh peer connected to every instance, as a robot on the fleet's network.
async fn robot_peer(endpoints: &[String]) -> zenoh::Session {
    let mut c = zenoh::Config::default();
    c.insert_json5("mode", "\"peer\"").unwrap();
    c.insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    c.insert_json5(
        "connect/endpoints",
        &serde_json::to_string(endpoints).unwrap(),
    )
    .unwrap();
    zenoh::open(c).await.unwrap()
}

/// `command` over `factord/rpc`, retried while the session moves (503 `session_moving`).
async fn rpc(z: &zenoh::Session, command: Value) -> Value {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        match zenoh_get(z, "factord/rpc", Some(&command)).await {
            Ok(v) => return v,
            Err(e) if e["error"]["code"] == "session_moving" => {
                assert!(Instant::now() < deadline, "{command}: still moving");
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            Err(e) => panic!("{command}: {e}"),
        }
    }
}

/// The latest value of each key that `samples` carried (JSON estimate events), every key
/// checked to be robot `robot`'s.
fn take(
    samples: &std::sync::mpsc::Receiver<Value>,
    robot: char,
    latest: &mut BTreeMap<u64, Vec<f64>>,
) {
    for event in samples.try_iter() {
        for v in event["variables"].as_array().unwrap() {
            let key = v["key"].as_u64().unwrap();
            assert_eq!(
                robot_of_key(key),
                Some(robot),
                "key {key} on {robot}'s stream"
            );
            latest.insert(key, serde_json::from_value(v["value"].clone()).unwrap());
        }
    }
}

fn values(estimate: &Value) -> BTreeMap<u64, Vec<f64>> {
    estimate["variables"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| {
            let key = v["key"].as_u64().unwrap();
            (key, serde_json::from_value(v["value"].clone()).unwrap())
        })
        .collect()
}

fn same(got: &BTreeMap<u64, Vec<f64>>, want: &BTreeMap<u64, Vec<f64>>) -> bool {
    got.len() == want.len()
        && got
            .iter()
            .zip(want)
            .all(|((k, g), (l, w))| k == l && g.iter().zip(w).all(|(a, b)| (a - b).abs() <= 1e-9))
}

#[tokio::test(flavor = "multi_thread")]
async fn a_robots_streams_follow_its_session_to_the_adopter() {
    let mut fleet = Fleet::start(2, &[]);
    let endpoints: Vec<String> = (0..2).map(|i| fleet.instance(i).zenoh.clone()).collect();
    let z = robot_peer(&endpoints).await;
    fleet.wait_settled(&z).await;
    rpc(
        &z,
        json!({"op": "create_session", "session": SESSION, "kind": "pose_graph_2d",
               "robots": {"min_closures": 2}}),
    )
    .await;
    let base = |r: char| format!("factord/{SESSION}/robot/{r}");
    let (_sub_a, a_poses) = json_samples(&z, &format!("{}/poses", base('a'))).await;
    let (_sub_b, b_odom) = json_samples(&z, &format!("{}/odom_poses", base('b'))).await;
    let (_sub_f, b_frames) = json_samples(&z, &format!("{}/map_from_odom", base('b'))).await;
    tokio::time::sleep(Duration::from_millis(500)).await;

    let (a, b) = (truth(0, 40), truth(13, 30));
    let apply = |batch: Value| json!({"op": "apply_batch", "session": SESSION, "batch": batch});
    rpc(&z, apply(robot_batch('a', &a, 0..30))).await;
    rpc(&z, apply(robot_batch('b', &b, 0..20))).await;
    rpc(
        &z,
        apply(json!({"factors": [closure(&a, 18, &b, 5), closure(&a, 22, &b, 9)]})),
    )
    .await;
    rpc(
        &z,
        json!({"op": "optimize", "session": SESSION, "wait": true}),
    )
    .await;

    // Both read their view from the first owner.
    let (mut a_latest, mut b_latest) = (BTreeMap::new(), BTreeMap::new());
    let deadline = Instant::now() + Duration::from_secs(20);
    while a_latest.len() < 30 || b_latest.len() < 20 {
        take(&a_poses, 'a', &mut a_latest);
        take(&b_odom, 'b', &mut b_latest);
        assert!(
            Instant::now() < deadline,
            "a has {} poses, b {}",
            a_latest.len(),
            b_latest.len()
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let merged = b_frames
        .recv_timeout(Duration::from_secs(10))
        .into_iter()
        .chain(b_frames.try_iter())
        .last()
        .expect("b's map_from_odom");
    assert_eq!(merged["in_map"], true, "{merged}");

    // kill -9 of the owner: the survivor adopts the session from the journal.
    let victim = fleet.owner(SESSION);
    fleet.kill(victim);
    let adopted_at = Instant::now();
    rpc(&z, apply(robot_batch('b', &b, 20..30))).await;
    rpc(
        &z,
        json!({"op": "optimize", "session": SESSION, "wait": true}),
    )
    .await;
    let want = rpc(
        &z,
        json!({"op": "get_estimate", "session": SESSION, "robot": "b", "frame": "odom"}),
    )
    .await;
    let want = values(&want);
    assert_eq!(want.len(), 30);
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        take(&b_odom, 'b', &mut b_latest);
        if same(&b_latest, &want) {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "b's odometry-frame stream did not follow the adopter: {} of 30 poses",
            b_latest.len()
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    println!(
        "b's stream complete from the adopter {:?} after the kill",
        adopted_at.elapsed()
    );
    for (i, _) in b.iter().enumerate() {
        let got = &b_latest[&robot_key('b', i as u64)];
        let d = sent(&b, i).between(&Se2::new(got[0], got[1], got[2]));
        assert!(
            d.x.hypot(d.y) < 1e-6 && d.theta.abs() < 1e-6,
            "b{i}: {got:?}"
        );
    }
    // The adopter answers the robot's queryables.
    let queried = zenoh_get(&z, &format!("{}/estimate?frame=odom", base('b')), None)
        .await
        .expect("b's estimate from the adopter");
    assert!(same(&values(&queried), &want));
    let frame = zenoh_get(&z, &format!("{}/map_from_odom", base('b')), None)
        .await
        .expect("b's frame from the adopter");
    assert_eq!(frame["map_from_odom"], merged["map_from_odom"], "{frame}");
    assert_eq!(frame["in_map"], true);
}
