//! Each robot gets its own view back over zenoh (issue 54 item 4): two robots start in unknown
//! frames and merge on three closures; each subscribes to its own keys
//! (`factord/<s>/robot/<id>/…`) and reads its trajectory back, in the map and in its own
//! odometry frame, JSON and binary. A robot's keys never carry another robot's poses, its
//! `map_from_odom` follows the merge as `GET …/robots` reports it, and the odometry-frame poses
//! are the HTTP `estimate?robot=b&frame=odom` and what the robot sent (the data are exact, so
//! the optimisation's correction is nil). Both topologies a robot can use: a peer of the
//! server, and a zenoh client of a router the server is a peer of.

use crate::common;

use std::collections::BTreeMap;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use common::server::{
    client, create, free_port, get, post, zenoh_get, zenoh_peer, zenoh_session, TestServer,
};
use common::square_walk::{closure, robot_batch, sent, truth};
use factord::api::poses_binary;
use factord::api::robots::{robot_key, robot_of_key};
use factord::geometry::Se2;
use serde_json::{json, Value};

const SESSION: &str = "rs";

/// Every sample under `key`, as (key, payload, encoding).
pub(crate) type Samples = mpsc::Receiver<(String, Vec<u8>, String)>;

pub(crate) async fn samples(
    z: &zenoh::Session,
    key: &str,
) -> (zenoh::pubsub::Subscriber<()>, Samples) {
    let (tx, rx) = mpsc::channel();
    let tx = std::sync::Mutex::new(tx);
    let subscriber = z
        .declare_subscriber(key.to_string())
        .callback(move |sample| {
            let _ = tx.lock().unwrap().send((
                sample.key_expr().to_string(),
                sample.payload().to_bytes().to_vec(),
                sample.encoding().to_string(),
            ));
        })
        .await
        .unwrap();
    (subscriber, rx)
}

/// What one robot read on its keys so far: the latest value of each key per stream, the
/// `map_from_odom` samples, and every key any estimate carried.
#[derive(Default)]
pub(crate) struct View {
    /// stream (`poses`, `odom_poses`, `bin/poses`, `bin/odom_poses`) → key → value.
    pub(crate) latest: BTreeMap<String, BTreeMap<u64, Vec<f64>>>,
    pub(crate) frames: Vec<Value>,
    keys_seen: Vec<u64>,
    samples: usize,
}

impl View {
    /// How many poses each stream holds, and the last frame: what a failure shows.
    pub(crate) fn summary(&self) -> String {
        let poses: Vec<_> = self.latest.iter().map(|(k, v)| (k, v.len())).collect();
        format!("{poses:?}, last frame {:?}", self.frames.last())
    }

    pub(crate) fn take(&mut self, rx: &Samples, base: &str) {
        for (key, payload, encoding) in rx.try_iter() {
            self.samples += 1;
            let stream = key
                .strip_prefix(base)
                .expect("under the robot's base")
                .to_string();
            if stream == "map_from_odom" {
                self.frames.push(serde_json::from_slice(&payload).unwrap());
                continue;
            }
            let variables: Vec<(u64, Vec<f64>)> = if stream.starts_with("bin/") {
                assert!(encoding.contains("octet-stream"), "{key}: {encoding}");
                let estimate = poses_binary::decode(&payload, SESSION).expect("binary poses");
                estimate
                    .variables
                    .iter()
                    .map(|v| (v.key, v.value.to_vec()))
                    .collect()
            } else {
                let event: Value = serde_json::from_slice(&payload).unwrap();
                assert_eq!(event["type"], "estimate", "{key}: {event}");
                event["variables"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|v| {
                        (
                            v["key"].as_u64().unwrap(),
                            serde_json::from_value(v["value"].clone()).unwrap(),
                        )
                    })
                    .collect()
            };
            let latest = self.latest.entry(stream).or_default();
            for (k, v) in variables {
                self.keys_seen.push(k);
                latest.insert(k, v);
            }
        }
    }
}

/// `estimate` (JSON) as key → value.
pub(crate) fn values(estimate: &Value) -> BTreeMap<u64, Vec<f64>> {
    estimate["variables"]
        .as_array()
        .unwrap_or_else(|| panic!("an estimate: {estimate}"))
        .iter()
        .map(|v| {
            (
                v["key"].as_u64().unwrap(),
                serde_json::from_value(v["value"].clone()).unwrap(),
            )
        })
        .collect()
}

pub(crate) fn same(
    got: &BTreeMap<u64, Vec<f64>>,
    want: &BTreeMap<u64, Vec<f64>>,
    tol: f64,
) -> bool {
    got.len() == want.len()
        && got.iter().zip(want).all(|((k, g), (l, w))| {
            k == l && g.len() == w.len() && g.iter().zip(w).all(|(a, b)| (a - b).abs() <= tol)
        })
}

fn pose(v: &[f64]) -> Se2 {
    Se2::new(v[0], v[1], v[2])
}

fn near(got: &Se2, want: &Se2, tol: f64) -> bool {
    let d = want.between(got);
    d.x.hypot(d.y) < tol && d.theta.abs() < tol
}

pub(crate) enum Topology {
    Peer,
    Router,
}

/// The router (to keep alive for the test) if any, the server, and the robots' zenoh session:
/// a peer of the server, or a client of a router the server is a peer of.
pub(crate) async fn connect(
    topology: Topology,
) -> (Option<zenoh::Session>, TestServer, zenoh::Session) {
    match topology {
        Topology::Peer => {
            let s = TestServer::start(&[]);
            let z = zenoh_peer(&s.zenoh).await;
            (None, s, z)
        }
        Topology::Router => {
            let endpoint = format!("tcp/127.0.0.1:{}", free_port());
            let router = zenoh_session("router", "listen", &endpoint).await;
            let s = TestServer::start(&["--zenoh-connect", &endpoint]);
            let z = zenoh_session("client", "connect", &endpoint).await;
            (Some(router), s, z)
        }
    }
}

/// A client, and session `name` created on `s`: 2D poses of robots that merge on three
/// closures.
pub(crate) async fn robots_session(s: &TestServer, name: &str) -> reqwest::Client {
    let c = client();
    let session = json!({"session": name, "kind": "pose_graph_2d", "robots": {"min_closures": 3}});
    create(&c, s, &session).await;
    c
}

async fn each_robot_reads_its_own_view(topology: Topology) {
    let (_router, s, z) = connect(topology).await;
    let c = robots_session(&s, SESSION).await;
    let url = |path: &str| s.url(&format!("/v1/sessions/{SESSION}{path}"));
    let base = |r: char| format!("factord/{SESSION}/robot/{r}/");
    let (_sub_a, rx_a) = samples(&z, &format!("{}**", base('a'))).await;
    let (_sub_b, rx_b) = samples(&z, &format!("{}**", base('b'))).await;
    // Declared last: once the server hears this one (an empty batch's ack arrives), it knows
    // the robots' subscriptions too (a session's declarations travel in order).
    let (_sub_acks, acks) = samples(&z, &format!("factord/{SESSION}/out/acks")).await;
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let (status, v) = post(&c, &url("/batches"), &json!({"variables": []})).await;
        assert_eq!(status, 200, "{v}");
        if acks.recv_timeout(Duration::from_millis(200)).is_ok() {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "the server never heard the subscriptions"
        );
    }

    let (a, b) = (truth(0, 40), truth(13, 30));
    let post_ok = |body: Value| {
        let (c, url) = (c.clone(), url("/batches"));
        async move {
            let (status, v) = post(&c, &url, &body).await;
            assert_eq!(status, 200, "{v}");
            v
        }
    };
    post_ok(robot_batch('a', &a, 0..30)).await;
    post_ok(robot_batch('b', &b, 0..20)).await;
    post_ok(json!({"factors": [closure(&a, 18, &b, 5)]})).await;
    post_ok(json!({"factors": [closure(&a, 22, &b, 9), closure(&a, 26, &b, 13)]})).await;
    post_ok(robot_batch('b', &b, 20..30)).await;
    let (status, v) = post(&c, &url("/optimize?wait=true"), &json!({})).await;
    assert_eq!(status, 200, "{v}");

    let (_, report) = get(&c, &url("/robots")).await;
    assert_eq!(report["merges"].as_array().unwrap().len(), 1, "{report}");
    let (_, a_map) = get(&c, &url("/estimate?robot=a")).await;
    let (_, a_odom) = get(&c, &url("/estimate?robot=a&frame=odom")).await;
    let (_, b_map) = get(&c, &url("/estimate?robot=b")).await;
    let (_, b_odom) = get(&c, &url("/estimate?robot=b&frame=odom")).await;
    let want = |robot: char, stream: &str| {
        let estimate = match (robot, stream.ends_with("odom_poses")) {
            ('a', false) => &a_map,
            ('a', true) => &a_odom,
            (_, false) => &b_map,
            (_, true) => &b_odom,
        };
        values(estimate)
    };
    let streams = ["poses", "odom_poses", "bin/poses", "bin/odom_poses"];

    let robot_report = |r: &str| {
        report["robots"]
            .as_array()
            .unwrap()
            .iter()
            .find(|x| x["robot"] == r)
            .cloned()
            .unwrap()
    };

    // The streams settle on the estimate the HTTP reads give, and the frames on the report.
    let (mut view_a, mut view_b) = (View::default(), View::default());
    let deadline = Instant::now() + Duration::from_secs(20);
    let settled = |view: &View, robot: char| {
        let frame = view.frames.last().map(|f| &f["map_from_odom"]);
        frame == Some(&robot_report(&robot.to_string())["map_from_odom"])
            && streams.iter().all(|stream| {
                view.latest
                    .get(*stream)
                    .is_some_and(|got| same(got, &want(robot, stream), 1e-9))
            })
    };
    loop {
        view_a.take(&rx_a, &base('a'));
        view_b.take(&rx_b, &base('b'));
        if settled(&view_a, 'a') && settled(&view_b, 'b') {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "the robots' streams did not settle on the estimate and the report in 20 s: a has \
             {}, b has {}",
            view_a.summary(),
            view_b.summary()
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    println!(
        "robot a: {} samples, robot b: {} samples",
        view_a.samples, view_b.samples
    );

    // A robot's keys carry its own poses only.
    for (robot, view) in [('a', &view_a), ('b', &view_b)] {
        assert!(!view.keys_seen.is_empty());
        for &k in &view.keys_seen {
            assert_eq!(
                robot_of_key(k),
                Some(robot),
                "key {k} on robot {robot}'s stream"
            );
        }
    }

    // In its odometry frame, each robot reads back what it sent (exact data: no correction).
    for (robot, world, view) in [('a', &a, &view_a), ('b', &b, &view_b)] {
        let odom = &view.latest["odom_poses"];
        assert_eq!(odom.len(), 30);
        for (i, _) in world.iter().enumerate().take(30) {
            let got = pose(&odom[&robot_key(robot, i as u64)]);
            assert!(
                near(&got, &sent(world, i), 1e-6),
                "{robot}{i} in its odometry frame: {got:?} vs {:?}",
                sent(world, i)
            );
            let in_map = pose(&view.latest["poses"][&robot_key(robot, i as u64)]);
            assert!(near(&in_map, &world[i], 1e-6), "{robot}{i} in the map");
        }
    }

    // map_from_odom: b alone (identity, not in the map) until the merge, then where the merge
    // put it, as GET …/robots says; a in the map from the start.
    // (Its first pose and the merge may fall in one run of events: then only the merged
    // frame is published, as the key carries the state when it is put.)
    for frame in view_b.frames.iter().filter(|f| f["in_map"] == false) {
        assert_eq!(frame["map_from_odom"], json!([0.0, 0.0, 0.0]), "{frame}");
        assert_eq!(frame["component"], json!(["b"]), "{frame}");
    }
    let last_b = view_b.frames.last().expect("b's map_from_odom published");
    assert_eq!(last_b["in_map"], true, "{last_b}");
    assert_eq!(last_b["session"], SESSION);
    assert_eq!(
        last_b["map_from_odom"],
        robot_report("b")["map_from_odom"],
        "{last_b} vs {report}"
    );
    let frame: Vec<f64> = serde_json::from_value(last_b["map_from_odom"].clone()).unwrap();
    assert!(near(&pose(&frame), &b[0], 1e-6), "map ← odom_b: {frame:?}");
    for frame in &view_a.frames {
        assert_eq!(frame["in_map"], true, "{frame}");
        assert_eq!(frame["map_from_odom"], json!([0.0, 0.0, 0.0]), "{frame}");
    }
    assert_eq!(
        view_a.frames.last().unwrap()["component"],
        json!(["a", "b"])
    );

    // The queryables answer as HTTP does.
    let queried = zenoh_get(&z, &format!("{}estimate?frame=odom", base('b')), None)
        .await
        .expect("b's estimate");
    assert!(same(&values(&queried), &values(&b_odom), 0.0));
    let queried = zenoh_get(&z, &format!("{}estimate", base('a')), None)
        .await
        .expect("a's estimate");
    assert!(same(&values(&queried), &values(&a_map), 0.0));
    let queried = zenoh_get(&z, &format!("{}map_from_odom", base('b')), None)
        .await
        .expect("b's frame");
    assert_eq!(queried["map_from_odom"], robot_report("b")["map_from_odom"]);
    assert_eq!(queried["component"], json!(["a", "b"]));

    // Bad input: typed error replies naming the field.
    for (selector, code, field) in [
        ("robot/c/estimate", "unknown_robot", "robot"),
        ("robot/c/map_from_odom", "unknown_robot", "robot"),
        ("robot/x41/estimate", "invalid_value", "robot"),
        ("robot/ab/map_from_odom", "invalid_value", "robot"),
        ("robot/b/estimate?robot=a", "invalid_value", "robot"),
        ("robot/b/estimate?from=3", "invalid_value", "robot"),
        ("robot/b/estimate?frame=up", "invalid_query", "frame"),
    ] {
        let selector = format!("factord/{SESSION}/{selector}");
        let e = zenoh_get(&z, &selector, None).await.expect_err(&selector);
        assert_eq!(e["error"]["code"], code, "{selector}: {e}");
        assert_eq!(e["error"]["field"], field, "{selector}: {e}");
    }
    let e = zenoh_get(&z, "factord/nosuch/robot/a/estimate", None)
        .await
        .expect_err("an unknown session");
    assert_eq!(e["error"]["code"], "unknown_session", "{e}");
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn each_robot_reads_its_own_view_as_a_peer() {
    each_robot_reads_its_own_view(Topology::Peer).await;
}

#[tokio::test(flavor = "multi_thread")]
async fn each_robot_reads_its_own_view_through_a_router() {
    each_robot_reads_its_own_view(Topology::Router).await;
}

/// The Python client's helpers for a robot's own keys (`subscribe_robot_poses`,
/// `subscribe_robot_frame`, `robot_estimate`, `robot_frame`) against this build
/// (`clients/python/tests/test_robot_streams.py`); skips without Python, as the client's tests.
#[test]
fn the_python_client_follows_a_robots_own_keys() {
    let repo = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let python = match common::python_venv(
        "client",
        &[
            vec!["jsonschema>=4.18".into(), "referencing".into()],
            vec![repo.join("clients/python").into()],
        ],
    ) {
        Ok(p) => p,
        Err(reason) => {
            let _: Option<()> =
                common::skip_or_fail(&format!("no Python environment for the client: {reason}"));
            return;
        }
    };
    let s = TestServer::start(&[]);
    common::run_python_script(
        &python,
        &s,
        "clients/python/tests/test_robot_streams.py",
        &[],
    );
}

/// A merge's moved values change at the merge's sequence and ride its batch's `estimate`
/// event: a `since` read right after the merge (no solve: manual policy) has robot b's poses
/// in the map. Before, the mirror moved them without marking them changed, so streams and
/// `since` reads kept b's pre-merge values until a solve changed them again.
#[tokio::test(flavor = "multi_thread")]
async fn a_merge_marks_the_moved_poses_changed_without_a_solve() {
    let s = TestServer::start(&[]);
    let c = client();
    let url = |path: &str| s.url(&format!("/v1/sessions/{SESSION}{path}"));
    create(
        &c,
        &s,
        &json!({"session": SESSION, "kind": "pose_graph_2d", "robots": {"min_closures": 3},
                "auto_optimize": {"policy": "manual"}}),
    )
    .await;
    let z = zenoh_peer(&s.zenoh).await;
    let (_sub, poses) = samples(&z, &format!("factord/{SESSION}/out/poses")).await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let (a, b) = (truth(0, 40), truth(13, 30));
    let mut sequence = 0;
    for body in [robot_batch('a', &a, 0..30), robot_batch('b', &b, 0..20)] {
        let (status, v) = post(&c, &url("/batches"), &body).await;
        assert_eq!(status, 200, "{v}");
        sequence = v["sequence"].as_u64().unwrap();
    }
    let closures = json!({"factors": [closure(&a, 18, &b, 5), closure(&a, 22, &b, 9), closure(&a, 26, &b, 13)]});
    let (status, v) = post(&c, &url("/batches"), &closures).await;
    assert_eq!(status, 200, "{v}");
    let merged_at = v["sequence"].as_u64().unwrap();
    let (_, report) = get(&c, &url("/robots")).await;
    assert_eq!(report["merges"][0]["sequence"], merged_at, "{report}");
    let (_, changed) = get(&c, &url(&format!("/estimate?since={sequence}"))).await;
    let changed = values(&changed);
    assert_eq!(changed.len(), 20, "b's 20 poses moved: {changed:?}");
    for (i, world) in b.iter().enumerate().take(20) {
        let got = pose(&changed[&robot_key('b', i as u64)]);
        assert!(
            near(&got, world, 1e-6),
            "b{i} in the map: {got:?} vs {world:?}"
        );
    }
    // The merge batch's estimate event carries them too.
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let carried = poses.try_iter().any(|(_, payload, _)| {
            let event: Value = serde_json::from_slice(&payload).unwrap();
            event["sequence"] == merged_at && values(&event).len() == 20
        });
        if carried {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "no estimate event of the merge's batch with b's 20 moved poses"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}
