//! 2D landmark SLAM in a `pose_graph_2d` session, over HTTP: poses streamed one by one with
//! odometry, `point2` landmarks added without a value (predicted from their first
//! `bearing_range_se2` sighting), later sightings closing the loop; the estimate after a solve
//! has every landmark where it is, and a sighting with a negative range or a point2 used as a
//! pose is refused naming the field. Landmarks seen by bearing only (`bearing_se2`) likewise.

use crate::common;

use common::server::{client, create, get, post, TestServer};
use serde_json::{json, Value};

const LANDMARK_BASE: u64 = 1000;

/// Pose k on a circle of radius 10 (heading along it), 8 landmarks on a circle of radius 14.
fn pose(k: usize) -> [f64; 3] {
    let a = k as f64 * 0.1;
    [
        10.0 * a.cos(),
        10.0 * a.sin(),
        a + std::f64::consts::FRAC_PI_2,
    ]
}

fn landmark(l: usize) -> [f64; 2] {
    let a = l as f64 * std::f64::consts::PI / 4.0;
    [14.0 * a.cos(), 14.0 * a.sin()]
}

/// Bearing and range of landmark `l` from pose `k` (exact).
fn sighting_of(k: usize, l: usize) -> [f64; 2] {
    let [x, y, th] = pose(k);
    let [lx, ly] = landmark(l);
    let (dx, dy) = (lx - x, ly - y);
    let (bx, by) = (
        th.cos() * dx + th.sin() * dy,
        -th.sin() * dx + th.cos() * dy,
    );
    [by.atan2(bx), bx.hypot(by)]
}

fn odometry(k: usize) -> [f64; 3] {
    let ([x0, y0, t0], [x1, y1, t1]) = (pose(k - 1), pose(k));
    let (dx, dy) = (x1 - x0, y1 - y0);
    [
        t0.cos() * dx + t0.sin() * dy,
        -t0.sin() * dx + t0.cos() * dy,
        t1 - t0,
    ]
}

/// The 70 batches of the circle walk: pose k (pose 0 fixed, the others from odometry), and
/// each landmark in view (bearing within 1.2 rad, range within 12 m) as `sighting(k, l, key)`
/// makes it; a landmark seen for the first time is also sent, as `first_seen(l, key)` makes it.
/// The landmarks seen, by index.
fn circle_batches(
    first_seen: impl Fn(usize, u64) -> Value,
    sighting: impl Fn(usize, usize, u64) -> Value,
) -> (Vec<Value>, std::collections::BTreeSet<usize>) {
    let mut seen = std::collections::BTreeSet::new();
    let mut batches = Vec::new();
    for k in 0..70 {
        let mut variables = vec![];
        let mut factors = vec![];
        if k == 0 {
            variables.push(json!({"key": 0, "kind": "se2", "value": pose(0), "fixed": true}));
        } else {
            variables.push(json!({"key": k, "kind": "se2"}));
            factors.push(json!({"type": "between_se2", "keys": [k - 1, k],
                "measurement": odometry(k), "sigmas": [0.05, 0.05, 0.01]}));
        }
        for l in 0..8 {
            let [b, r] = sighting_of(k, l);
            if b.abs() > 1.2 || r > 12.0 {
                continue; // out of the sensor's view
            }
            let key = LANDMARK_BASE + l as u64;
            if seen.insert(l) {
                variables.push(first_seen(l, key));
            }
            factors.push(sighting(k, l, key));
        }
        batches.push(json!({"variables": variables, "factors": factors}));
    }
    (batches, seen)
}

/// Every landmark of `estimate` where it is (1e-6); how many were checked.
fn assert_landmarks_in_place(estimate: &Value) -> usize {
    let mut checked = 0;
    for v in estimate["variables"].as_array().unwrap() {
        let key = v["key"].as_u64().unwrap();
        if key >= LANDMARK_BASE {
            assert_eq!(v["kind"], "point2", "{v}");
            let [lx, ly] = landmark((key - LANDMARK_BASE) as usize);
            let value: Vec<f64> = serde_json::from_value(v["value"].clone()).unwrap();
            assert!(
                (value[0] - lx).abs() < 1e-6 && (value[1] - ly).abs() < 1e-6,
                "{v}"
            );
            checked += 1;
        }
    }
    checked
}

#[tokio::test(flavor = "multi_thread")]
async fn landmarks_stream_into_a_pose_graph_session() {
    let s = TestServer::start(&[]);
    let c = client();
    create(
        &c,
        &s,
        &json!({"session": "trees", "kind": "pose_graph_2d"}),
    )
    .await;
    let url = s.url("/v1/sessions/trees/batches");
    // Landmarks start where their first sighting puts them.
    let (batches, seen) = circle_batches(
        |_, key| json!({"key": key, "kind": "point2"}),
        |k, l, key| {
            json!({"type": "bearing_range_se2", "keys": [k, key],
                "measurement": sighting_of(k, l), "sigmas": [0.01, 0.05]})
        },
    );
    for (k, batch) in batches.iter().enumerate() {
        let (status, ack) = post(&c, &url, batch).await;
        assert!(status < 300, "pose {k}: {ack}");
    }
    assert!(seen.len() >= 6, "landmarks seen: {seen:?}");
    let (status, solved) = post(
        &c,
        &s.url("/v1/sessions/trees/optimize?wait=true"),
        &json!({}),
    )
    .await;
    assert_eq!(status, 200, "{solved}");
    let (status, estimate) = get(&c, &s.url("/v1/sessions/trees/estimate")).await;
    assert_eq!(status, 200);
    let checked = assert_landmarks_in_place(&estimate);
    assert_eq!(checked, seen.len());
    let (_, info) = get(&c, &s.url("/v1/sessions/trees")).await;
    assert!(info["chi2"].as_f64().unwrap_or(f64::NAN) < 1e-9, "{info}");

    // Refusals name the field; nothing is applied.
    let bad: Value = json!({"factors": [{"type": "bearing_range_se2", "keys": [1, LANDMARK_BASE],
        "measurement": [0.1, -2.0], "sigmas": [0.01, 0.05]}]});
    let (status, e) = post(&c, &url, &bad).await;
    assert_eq!(status, 400, "{e}");
    assert_eq!(e["error"]["field"], "factors[0].measurement", "{e}");
    let swapped = json!({"factors": [{"type": "bearing_range_se2", "keys": [LANDMARK_BASE, 1],
        "measurement": [0.1, 2.0], "sigmas": [0.01, 0.05]}]});
    let (status, e) = post(&c, &url, &swapped).await;
    assert_eq!(status, 422, "{e}");
    assert_eq!(e["error"]["code"], "wrong_kind", "{e}");
    assert_eq!(e["error"]["field"], "factors[0].keys[0]", "{e}");
    s.assert_no_panic();
}

/// Landmarks seen by bearing only (`bearing_se2`) from the circle of poses: each is sent with a
/// value a metre off and ends where it is; a landmark without a value, which one bearing cannot
/// place, is refused naming it.
#[tokio::test(flavor = "multi_thread")]
async fn bearing_only_sightings_place_landmarks_in_a_session() {
    let s = TestServer::start(&[]);
    let c = client();
    create(
        &c,
        &s,
        // A landmark seen from one place is free along its ray until a second sighting:
        // Levenberg-Marquardt's damping holds it where it is meanwhile (Gauss-Newton would
        // call the system indeterminate at it).
        &json!({"session": "bearings", "kind": "pose_graph_2d",
            "options": {"method": "levenberg_marquardt"}}),
    )
    .await;
    let url = s.url("/v1/sessions/bearings/batches");
    let (batches, seen) = circle_batches(
        |l, key| {
            let [lx, ly] = landmark(l);
            json!({"key": key, "kind": "point2", "value": [lx + 0.8, ly - 0.6]})
        },
        |k, l, key| {
            json!({"type": "bearing_se2", "keys": [k, key],
                "measurement": [sighting_of(k, l)[0]], "sigmas": [0.01]})
        },
    );
    for (k, batch) in batches.iter().enumerate() {
        let (status, ack) = post(&c, &url, batch).await;
        assert!(status < 300, "pose {k}: {ack}");
    }
    assert!(seen.len() >= 6, "landmarks seen: {seen:?}");
    let optimize = s.url("/v1/sessions/bearings/optimize?wait=true");
    let (status, solved) = post(&c, &optimize, &json!({})).await;
    assert_eq!(status, 200, "{solved}");
    let (_, estimate) = get(&c, &s.url("/v1/sessions/bearings/estimate")).await;
    let checked = assert_landmarks_in_place(&estimate);
    assert_eq!(checked, seen.len());

    let unplaced = json!({"variables": [{"key": LANDMARK_BASE + 50, "kind": "point2"}],
        "factors": [{"type": "bearing_se2", "keys": [3, LANDMARK_BASE + 50],
        "measurement": [0.2], "sigmas": [0.01]}]});
    let (status, e) = post(&c, &url, &unplaced).await;
    assert!((400..500).contains(&status), "{status} {e}");
    assert_eq!(e["error"]["field"], "variables[0].value", "{e}");
    s.assert_no_panic();
}
