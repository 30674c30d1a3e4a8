//! Several robots in one session (issue 54): two robots start in unknown frames, each sends
//! its values in its own odometry frame; one closure between them is held, a wrong one is
//! rejected, three that agree merge robot b into a's map; a's and b's later values land in the
//! map, and a kill -9 and restart replays the same merge from the journal.

use crate::common;

use std::time::Instant;

use common::server::{client, create, get, post, zenoh_get, TestServer};
use common::square_walk::{robot_batch, truth, INFO};
use factord::api::robots::robot_key;
use factord::geometry::Se2;
use serde_json::{json, Value};

fn between(a: &Se2, b: &Se2) -> Vec<f64> {
    a.between(b).to_array().to_vec()
}

fn closure(a: &[Se2], i: usize, b: &[Se2], j: usize, error: [f64; 3]) -> Value {
    let mut z = between(&a[i], &b[j]);
    (0..3).for_each(|k| z[k] += error[k]);
    json!({"type": "between_se2", "keys": [robot_key('a', i as u64), robot_key('b', j as u64)],
           "measurement": z, "information": INFO})
}

async fn batch(c: &reqwest::Client, s: &TestServer, body: Value) -> Value {
    let (status, ack) = post(c, &s.url("/v1/sessions/fleet/batches"), &body).await;
    assert_eq!(status, 200, "{ack}");
    ack
}

async fn optimized(c: &reqwest::Client, s: &TestServer) -> Value {
    let (status, v) = post(
        c,
        &s.url("/v1/sessions/fleet/optimize?wait=true"),
        &json!({}),
    )
    .await;
    assert_eq!(status, 200, "{v}");
    let (_, estimate) = get(c, &s.url("/v1/sessions/fleet/estimate")).await;
    estimate
}

/// The estimate's value of `key` as a pose.
fn pose(estimate: &Value, key: u64) -> Se2 {
    let v = estimate["variables"]
        .as_array()
        .unwrap()
        .iter()
        .find(|v| v["key"] == key)
        .unwrap_or_else(|| panic!("{key} in the estimate"));
    let x: Vec<f64> = serde_json::from_value(v["value"].clone()).unwrap();
    Se2::new(x[0], x[1], x[2])
}

fn assert_near(got: &Se2, want: &Se2, tol: f64, what: &str) {
    let d = want.between(got);
    assert!(
        d.x.hypot(d.y) < tol && d.theta.abs() < tol,
        "{what}: {got:?} vs {want:?}"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn two_robots_in_unknown_frames_merge_on_closures_that_agree() {
    let s = TestServer::start(&[]);
    let c = client();
    create(
        &c,
        &s,
        &json!({"session": "fleet", "kind": "pose_graph_2d", "robots": {}}),
    )
    .await;
    // Robot b starts 13 poses along a's square (x = 3, y = 0), in its own frame.
    let (a, b) = (truth(0, 40), truth(13, 30));
    batch(&c, &s, robot_batch('a', &a, 0..30)).await;
    batch(&c, &s, robot_batch('b', &b, 0..20)).await;
    let (_, report) = get(&c, &s.url("/v1/sessions/fleet/robots")).await;
    let robots = report["robots"].as_array().unwrap();
    assert_eq!(robots.len(), 2, "{report}");
    assert_eq!(robots[1]["robot"], "b");
    assert_eq!(robots[1]["in_map"], false, "{report}");
    assert_eq!(robots[1]["map_from_odom"], json!([0.0, 0.0, 0.0]));

    // One closure (b5 is a18): held, the map unchanged.
    let held = batch(
        &c,
        &s,
        json!({"factors": [closure(&a, 18, &b, 5, [0.0; 3])]}),
    )
    .await;
    let estimate = optimized(&c, &s).await;
    assert_near(
        &pose(&estimate, robot_key('b', 0)),
        &Se2::identity(),
        1e-9,
        "b0 before a merge",
    );
    let (_, report) = get(&c, &s.url("/v1/sessions/fleet/robots")).await;
    assert_eq!(
        report["pending"][0]["factor_id"], held["factor_ids"][0],
        "{report}"
    );
    assert!(report["merges"].as_array().unwrap().is_empty());

    // A wrong closure (5 m off) and two right ones: three agree, the wrong one is rejected.
    let wrong = batch(
        &c,
        &s,
        json!({"factors": [closure(&a, 25, &b, 2, [5.0, -1.0, 0.3])]}),
    )
    .await;
    let right = batch(
        &c,
        &s,
        json!({"factors": [closure(&a, 22, &b, 9, [0.0; 3]), closure(&a, 26, &b, 13, [0.0; 3])]}),
    )
    .await;
    let (_, report) = get(&c, &s.url("/v1/sessions/fleet/robots")).await;
    let merge = &report["merges"][0];
    assert_eq!(merge["kept"], json!(["a"]), "{report}");
    assert_eq!(merge["moved"], json!(["b"]));
    let mut merged: Vec<u64> = serde_json::from_value(merge["closures"].clone()).unwrap();
    merged.sort_unstable();
    let mut want = vec![held["factor_ids"][0].as_u64().unwrap()];
    want.extend(
        right["factor_ids"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap()),
    );
    assert_eq!(merged, want, "{report}");
    assert_eq!(merge["rejected"], json!([wrong["factor_ids"][0]]));
    assert_eq!(report["rejected"][0]["factor_id"], wrong["factor_ids"][0]);
    assert!(report["pending"].as_array().unwrap().is_empty(), "{report}");
    let b_robot = &report["robots"][1];
    assert_eq!(b_robot["in_map"], true);
    assert_eq!(b_robot["component"], json!(["a", "b"]));
    let frame: Vec<f64> = serde_json::from_value(b_robot["map_from_odom"].clone()).unwrap();
    assert_near(
        &Se2::new(frame[0], frame[1], frame[2]),
        &b[0],
        1e-6,
        "map ← odom_b",
    );

    // b's later poses, still in its odometry frame, land in the map; so does the estimate.
    batch(&c, &s, robot_batch('b', &b, 20..30)).await;
    let estimate = optimized(&c, &s).await;
    for (i, want) in b.iter().enumerate() {
        assert_near(
            &pose(&estimate, robot_key('b', i as u64)),
            want,
            1e-6,
            &format!("b{i}"),
        );
    }
    assert_near(&pose(&estimate, robot_key('a', 29)), &a[29], 1e-6, "a29");

    // Each robot reads its trajectory back in the map and in its own odometry frame.
    let (_, in_odom) = get(&c, &s.url("/v1/sessions/fleet/estimate?robot=b&frame=odom")).await;
    let (_, in_map) = get(&c, &s.url("/v1/sessions/fleet/estimate?robot=b")).await;
    assert_eq!(
        in_odom["variables"].as_array().unwrap().len(),
        30,
        "{in_odom}"
    );
    for (i, world) in b.iter().enumerate() {
        let key = robot_key('b', i as u64);
        let odom = b[0].inverse().compose(world);
        assert_near(
            &pose(&in_odom, key),
            &odom,
            1e-6,
            &format!("b{i} in odom_b"),
        );
        assert_near(
            &pose(&in_map, key),
            world,
            1e-6,
            &format!("b{i} in the map"),
        );
    }
    for (query, status, field) in [
        ("robot=c", 404, "robot"),
        ("robot=bb", 400, "robot"),
        ("frame=odom", 400, "frame"),
        ("robot=b&from=3", 400, "robot"),
    ] {
        let (got, e) = get(&c, &s.url(&format!("/v1/sessions/fleet/estimate?{query}"))).await;
        assert_eq!(got, status, "{query}: {e}");
        assert_eq!(e["error"]["field"], field, "{query}: {e}");
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn two_robots_merge_over_zenoh_and_the_merge_is_an_event() {
    let s = TestServer::start(&[]);
    let z = common::server::zenoh_peer(&s.zenoh).await;
    let rpc = |command: Value| {
        let z = z.clone();
        async move { zenoh_get(&z, "factord/rpc", Some(&command)).await }
    };
    rpc(
        json!({"op": "create_session", "session": "zr", "kind": "pose_graph_2d",
               "robots": {"min_closures": 2}}),
    )
    .await
    .unwrap();
    let (_sub, merges) = common::server::json_samples(&z, "factord/zr/out/merges").await;
    tokio::time::sleep(std::time::Duration::from_millis(300)).await;
    let (a, b) = (truth(0, 40), truth(13, 30));
    let closures =
        json!({"factors": [closure(&a, 18, &b, 5, [0.0; 3]), closure(&a, 22, &b, 9, [0.0; 3])]});
    for batch in [
        robot_batch('a', &a, 0..30),
        robot_batch('b', &b, 0..30),
        closures,
    ] {
        rpc(json!({"op": "apply_batch", "session": "zr", "batch": batch}))
            .await
            .unwrap();
    }
    let event = merges
        .recv_timeout(std::time::Duration::from_secs(10))
        .expect("a merge event on out/merges");
    assert_eq!(event["type"], "merge", "{event}");
    assert_eq!(event["moved"], json!(["b"]), "{event}");
    rpc(json!({"op": "optimize", "session": "zr", "wait": true}))
        .await
        .unwrap();
    let in_odom =
        rpc(json!({"op": "get_estimate", "session": "zr", "robot": "b", "frame": "odom"}))
            .await
            .unwrap();
    for (i, world) in b.iter().enumerate() {
        let odom = b[0].inverse().compose(world);
        assert_near(
            &pose(&in_odom, robot_key('b', i as u64)),
            &odom,
            1e-6,
            &format!("b{i}"),
        );
    }
    let report = rpc(json!({"op": "list_robots", "session": "zr"}))
        .await
        .unwrap();
    assert_eq!(
        report["robots"][1]["component"],
        json!(["a", "b"]),
        "{report}"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn a_merge_replays_from_the_journal_after_kill_9() {
    // A snapshot every 2 entries would compact the merge away: sessions with robots keep their
    // journal whole (see `maybe_snapshot`).
    let dir = common::temp_dir("robots-journal");
    let config = dir.with_extension("json");
    std::fs::write(
        &config,
        json!({"journal": {"snapshot_every": 2}}).to_string(),
    )
    .unwrap();
    let config = config.display().to_string();
    let extra = ["--config", config.as_str(), "--log", "info"];
    let s = TestServer::start_at(&dir, &extra, &[]);
    let c = client();
    create(
        &c,
        &s,
        &json!({"session": "fleet", "kind": "pose_graph_2d", "robots": {"min_closures": 2}}),
    )
    .await;
    let (a, b) = (truth(0, 40), truth(13, 30));
    batch(&c, &s, robot_batch('a', &a, 0..30)).await;
    batch(&c, &s, robot_batch('b', &b, 0..20)).await;
    batch(
        &c,
        &s,
        json!({"factors": [closure(&a, 25, &b, 2, [5.0, -1.0, 0.3])]}),
    )
    .await;
    batch(
        &c,
        &s,
        json!({"factors": [closure(&a, 18, &b, 5, [0.0; 3]), closure(&a, 22, &b, 9, [0.0; 3])]}),
    )
    .await;
    // After the merge, b's next poses arrive without values: the server predicts them (in the
    // map) from b's odometry.
    let mut predicted = robot_batch('b', &b, 20..30);
    for v in predicted["variables"].as_array_mut().unwrap() {
        v.as_object_mut().unwrap().remove("value");
    }
    batch(&c, &s, predicted).await;
    let before = optimized(&c, &s).await;
    let (_, report_before) = get(&c, &s.url("/v1/sessions/fleet/robots")).await;
    assert_eq!(
        report_before["merges"].as_array().unwrap().len(),
        1,
        "{report_before}"
    );

    // Time for a snapshot to be written, were one started.
    tokio::time::sleep(std::time::Duration::from_millis(500)).await;
    assert!(!s.stderr().contains("snapshot written"), "{}", s.stderr());
    s.kill();
    // The journal keeps those predictions in b's odometry frame, as b would have sent them: a
    // replay moves a robot's values into the map.
    let journal = std::fs::read(dir.join("sessions/fleet/journal.log")).unwrap();
    let journal = String::from_utf8_lossy(&journal);
    for i in 20..30 {
        let head = format!(r#"{{"key":{},"kind":"se2","value":["#, robot_key('b', i));
        let at = journal
            .find(&head)
            .unwrap_or_else(|| panic!("b{i} journalled"))
            + head.len();
        let end = at + journal[at..].find(']').unwrap();
        let value: Vec<f64> = journal[at..end]
            .split(',')
            .map(|x| x.parse().unwrap())
            .collect();
        let odom = b[0].inverse().compose(&b[i as usize]);
        assert_near(
            &Se2::new(value[0], value[1], value[2]),
            &odom,
            1e-6,
            &format!("journalled b{i}"),
        );
    }
    let s = TestServer::start_at(&dir, &extra, &[]);
    let since = Instant::now();
    common::server::recovered(&c, &s, "fleet", since).await;
    let after = optimized(&c, &s).await;
    let (_, report_after) = get(&c, &s.url("/v1/sessions/fleet/robots")).await;
    for field in ["robots", "pending", "rejected"] {
        assert_eq!(report_after[field], report_before[field], "{field}");
    }
    let (m0, m1) = (&report_before["merges"][0], &report_after["merges"][0]);
    for field in [
        "kept",
        "moved",
        "transform",
        "closures",
        "rejected",
        "sequence",
    ] {
        assert_eq!(m0[field], m1[field], "{field}");
    }
    for i in 0..30 {
        let key = robot_key('b', i);
        assert_near(
            &pose(&after, key),
            &pose(&before, key),
            1e-6,
            &format!("b{i} after restart"),
        );
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn robots_options_are_checked() {
    let s = TestServer::start(&[]);
    let c = client();
    for (body, field) in [
        (
            json!({"kind": "pose_graph_2d", "robots": {"min_closures": 1}}),
            "robots.min_closures",
        ),
        (json!({"kind": "bundle_adjustment", "robots": {}}), "robots"),
        (
            json!({"kind": "pose_graph_2d", "robots": {"min": 2}}),
            "robots",
        ),
    ] {
        let (status, e) = post(&c, &s.url("/v1/sessions"), &body).await;
        assert_eq!(status, 400, "{body}: {e}");
        let named = e["error"]["field"].as_str().unwrap_or("");
        assert!(named.starts_with(field), "{body}: {e}");
    }
    create(&c, &s, &json!({"session": "one", "kind": "pose_graph_2d"})).await;
    let (status, e) = get(&c, &s.url("/v1/sessions/one/robots")).await;
    assert_eq!(status, 400, "{e}");
    assert_eq!(e["error"]["code"], "no_robots");
}

/// A pose on a rising helix (radius 8 m, 0.3 m up per step, 12 steps a turn), facing along it
/// and rolled a little, as a drone's would be.
fn helix(i: usize) -> factord::geometry::Se3 {
    use nalgebra::{UnitQuaternion, Vector3};
    let a = i as f64 * std::f64::consts::TAU / 12.0;
    let rotation =
        UnitQuaternion::from_euler_angles(0.1 * a.sin(), 0.05, a + std::f64::consts::FRAC_PI_2);
    factord::geometry::Se3::new(
        rotation,
        Vector3::new(8.0 * a.cos(), 8.0 * a.sin(), 0.3 * i as f64),
    )
}

fn se3_wire(p: &factord::geometry::Se3) -> Vec<f64> {
    let (t, q) = (p.translation, p.rotation.quaternion());
    vec![t.x, t.y, t.z, q.i, q.j, q.k, q.w]
}

#[tokio::test(flavor = "multi_thread")]
async fn two_robots_in_3d_merge_and_read_back_their_own_frames() {
    let s = TestServer::start(&[]);
    let c = client();
    create(
        &c,
        &s,
        &json!({"session": "fleet", "kind": "pose_graph_3d", "robots": {"min_closures": 2}}),
    )
    .await;
    // Robot a flies the helix from pose 0, robot b from pose 5 (its own origin there).
    let a: Vec<_> = (0..24).map(helix).collect();
    let b: Vec<_> = (5..29).map(helix).collect();
    let mut info = vec![0.0; 21];
    let diagonal = [0usize, 6, 11, 15, 18, 20];
    for (k, &at) in diagonal.iter().enumerate() {
        info[at] = if k < 3 { 100.0 } else { 400.0 };
    }
    let robot = |r: char, poses: &[factord::geometry::Se3]| {
        let origin = poses[0].inverse();
        let variables: Vec<Value> = (0..poses.len())
            .map(|i| {
                json!({"key": robot_key(r, i as u64), "kind": "se3",
                           "value": se3_wire(&origin.compose(&poses[i]))})
            })
            .collect();
        let factors: Vec<Value> = (1..poses.len())
            .map(|i| json!({"type": "between_se3", "keys": [robot_key(r, i as u64 - 1), robot_key(r, i as u64)],
                           "measurement": se3_wire(&poses[i - 1].between(&poses[i])), "information": info}))
            .collect();
        json!({"variables": variables, "factors": factors})
    };
    batch(&c, &s, robot('a', &a)).await;
    batch(&c, &s, robot('b', &b)).await;
    // b's pose j is a's pose j + 5: two closures that agree merge b into a's map.
    let closures: Vec<Value> = [(8usize, 3usize), (15, 10)]
        .iter()
        .map(|&(i, j)| json!({"type": "between_se3", "keys": [robot_key('a', i as u64), robot_key('b', j as u64)],
                              "measurement": se3_wire(&a[i].between(&b[j])), "information": info}))
        .collect();
    batch(&c, &s, json!({"factors": closures})).await;
    let (_, report) = get(&c, &s.url("/v1/sessions/fleet/robots")).await;
    assert_eq!(report["merges"].as_array().unwrap().len(), 1, "{report}");
    assert_eq!(report["robots"][1]["component"], json!(["a", "b"]));
    let frame: Vec<f64> =
        serde_json::from_value(report["robots"][1]["map_from_odom"].clone()).unwrap();
    // The map is a's odometry frame: a's first pose at the origin.
    let map = a[0].inverse();
    let start = se3_wire(&map.compose(&b[0]));
    let sign = if frame[6] * start[6] < 0.0 { -1.0 } else { 1.0 }; // q and -q are one rotation
    for k in 0..7 {
        let want = if k < 3 { start[k] } else { sign * start[k] };
        assert!(
            (frame[k] - want).abs() < 1e-6,
            "map_from_odom {frame:?} vs b's start {start:?}"
        );
    }
    let (status, v) = post(
        &c,
        &s.url("/v1/sessions/fleet/optimize?wait=true"),
        &json!({}),
    )
    .await;
    assert_eq!(status, 200, "{v}");
    for (frame, origin) in [("map", map), ("odom", b[0].inverse())] {
        let (_, estimate) = get(
            &c,
            &s.url(&format!(
                "/v1/sessions/fleet/estimate?robot=b&frame={frame}"
            )),
        )
        .await;
        for (j, truth) in b.iter().enumerate() {
            let v = estimate["variables"]
                .as_array()
                .unwrap()
                .iter()
                .find(|v| v["key"] == robot_key('b', j as u64))
                .expect("b's pose");
            let got: Vec<f64> = serde_json::from_value(v["value"].clone()).unwrap();
            let want = se3_wire(&origin.compose(truth));
            let d = (0..3)
                .map(|k| (got[k] - want[k]).powi(2))
                .sum::<f64>()
                .sqrt();
            let dot: f64 = (3..7).map(|k| got[k] * want[k]).sum();
            assert!(
                d < 1e-6 && dot.abs() > 1.0 - 1e-9,
                "b{j} in {frame}: {got:?} vs {want:?}"
            );
        }
    }
}
