//! Issue 18, item 2, through a real server over HTTP: a `pose_graph_3d` session with `point3`
//! landmarks seen as body-frame positions (`position_se3_point3`, sent without a value and
//! started from their first sighting), UWB ranges to fixed beacons (`range_se3_point3`) and
//! between poses (`range_se3`), and GNSS fixes of an antenna on a lever arm
//! (`gnss_lever_arm_se3`). Poses start from perturbed values, with no odometry; the exact
//! measurements pull everything onto the truth. A 2D session does the same with
//! `range_se2_point2` and `range_se2`. Bad measurements are refused naming the field.

use crate::common;

use common::server::{client, create, get, post, TestServer};
use factord::geometry::{so3, Se3};
use nalgebra::Vector3;
use serde_json::{json, Value};

fn se3_json(x: &Se3) -> Value {
    let q = x.rotation.quaternion();
    let t = x.translation;
    json!([t.x, t.y, t.z, q.i, q.j, q.k, q.w])
}

/// Pose k of a climbing turn.
fn truth(k: usize) -> Se3 {
    let a = 0.3 * k as f64;
    Se3::new(
        so3::exp(&Vector3::new(0.02 * k as f64, 0.0, a)),
        Vector3::new(5.0 * a.cos(), 5.0 * a.sin(), 0.2 * k as f64),
    )
}

fn estimate_of(estimate: &Value, key: u64) -> Vec<f64> {
    let v = estimate["variables"]
        .as_array()
        .unwrap()
        .iter()
        .find(|v| v["key"] == key)
        .unwrap_or_else(|| panic!("variable {key} in the estimate"));
    serde_json::from_value(v["value"].clone()).unwrap()
}

#[tokio::test(flavor = "multi_thread")]
async fn landmarks_ranges_and_lever_arm_fixes_pull_a_3d_session_onto_the_truth() {
    let s = TestServer::start(&[]);
    let c = client();
    create(&c, &s, &json!({"session": "uwb", "kind": "pose_graph_3d"})).await;
    let poses = 12;
    let lever = Vector3::new(0.3, -0.1, 0.8);
    let beacons = [
        Vector3::new(8.0, 0.0, 1.0),
        Vector3::new(-6.0, 5.0, 2.0),
        Vector3::new(0.0, -7.0, 0.0),
        Vector3::new(1.0, 1.0, 6.0),
    ];
    let landmarks = [Vector3::new(3.0, 3.0, 1.0), Vector3::new(-2.0, 4.0, 0.5)];
    let mut variables = vec![];
    let mut factors = vec![];
    for (b, p) in beacons.iter().enumerate() {
        variables.push(
            json!({"key": 100 + b, "kind": "point3", "value": [p.x, p.y, p.z], "fixed": true}),
        );
    }
    for k in 0..poses {
        let x = truth(k);
        // Perturbed start: 0.3 m and 0.1 rad off.
        let off = Se3::new(
            so3::exp(&Vector3::new(0.1, -0.05, 0.1)),
            Vector3::new(0.3, -0.2, 0.1),
        );
        variables.push(json!({"key": k, "kind": "se3", "value": se3_json(&x.compose(&off))}));
        let antenna = x.translation + x.rotation_matrix() * lever;
        factors.push(json!({"type": "gnss_lever_arm_se3", "keys": [k],
            "measurement": [antenna.x, antenna.y, antenna.z, lever.x, lever.y, lever.z],
            "sigmas": [0.05, 0.05, 0.05]}));
        for (b, p) in beacons.iter().enumerate() {
            factors.push(json!({"type": "range_se3_point3", "keys": [k, 100 + b],
                "measurement": [(p - x.translation).norm()], "sigmas": [0.02]}));
        }
        if k > 0 {
            let d = (x.translation - truth(k - 1).translation).norm();
            factors.push(json!({"type": "range_se3", "keys": [k - 1, k],
                "measurement": [d], "sigmas": [0.02]}));
        }
    }
    let (status, ack) = post(
        &c,
        &s.url("/v1/sessions/uwb/batches"),
        &json!({"variables": variables, "factors": factors}),
    )
    .await;
    assert!(status < 300, "{ack}");
    // Landmarks seen from every pose (with the lever-arm fixes they fix each orientation; a
    // single fix leaves the turn about the lever arm open), sent without a value: each starts
    // from its first sighting.
    let mut variables = vec![];
    let mut factors = vec![];
    for (m, l) in landmarks.iter().enumerate() {
        variables.push(json!({"key": 200 + m, "kind": "point3"}));
        for k in 0..poses {
            let x = truth(k);
            let z = x.rotation_matrix().transpose() * (l - x.translation);
            factors.push(json!({"type": "position_se3_point3", "keys": [k, 200 + m],
                "measurement": [z.x, z.y, z.z], "sigmas": [0.05, 0.05, 0.05]}));
        }
    }
    let (status, ack) = post(
        &c,
        &s.url("/v1/sessions/uwb/batches"),
        &json!({"variables": variables, "factors": factors}),
    )
    .await;
    assert!(status < 300, "{ack}");
    let predicted: Vec<u64> = serde_json::from_value(ack["predicted"].clone()).unwrap();
    assert_eq!(predicted, [200, 201], "{ack}");

    let (status, solved) = post(
        &c,
        &s.url("/v1/sessions/uwb/optimize?wait=true"),
        &json!({}),
    )
    .await;
    assert_eq!(status, 200, "{solved}");
    let (_, estimate) = get(&c, &s.url("/v1/sessions/uwb/estimate")).await;
    for k in 0..poses {
        let v = estimate_of(&estimate, k as u64);
        let t = Vector3::new(v[0], v[1], v[2]);
        assert!(
            (t - truth(k).translation).norm() < 1e-6,
            "pose {k}: {v:?} {solved}"
        );
    }
    for (m, l) in landmarks.iter().enumerate() {
        let v = estimate_of(&estimate, 200 + m as u64);
        assert!(
            (Vector3::new(v[0], v[1], v[2]) - l).norm() < 1e-6,
            "landmark {m}: {v:?}"
        );
    }
    let (_, info) = get(&c, &s.url("/v1/sessions/uwb")).await;
    assert!(info["chi2"].as_f64().unwrap() < 1e-9, "{info}");

    // Refusals name the field.
    for (factor, field) in [
        (
            json!({"type": "range_se3", "keys": [0, 1], "measurement": [-1.0], "sigmas": [0.1]}),
            "factors[0].measurement",
        ),
        (
            json!({"type": "gnss_lever_arm_se3", "keys": [0], "measurement": [1.0, 2.0, 3.0], "sigmas": [0.1, 0.1, 0.1]}),
            "factors[0].measurement",
        ),
        (
            json!({"type": "position_se3_point3", "keys": [200, 0], "measurement": [1.0, 2.0, 3.0], "sigmas": [0.1, 0.1, 0.1]}),
            "factors[0].keys[0]",
        ),
    ] {
        let (status, e) = post(
            &c,
            &s.url("/v1/sessions/uwb/batches"),
            &json!({"factors": [factor]}),
        )
        .await;
        assert!(status == 400 || status == 422, "{e}");
        assert_eq!(e["error"]["field"], field, "{e}");
    }
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn ranges_pull_a_2d_session_onto_the_truth() {
    let s = TestServer::start(&[]);
    let c = client();
    create(&c, &s, &json!({"session": "uwb2", "kind": "pose_graph_2d"})).await;
    let beacons = [[6.0, 0.0], [-4.0, 5.0], [0.0, -6.0]];
    let truth = |k: usize| [k as f64, 0.5 * (k as f64).sin()];
    let mut variables = vec![];
    let mut factors = vec![];
    for (b, p) in beacons.iter().enumerate() {
        variables.push(json!({"key": 100 + b, "kind": "point2", "value": p, "fixed": true}));
    }
    for k in 0..8 {
        let [x, y] = truth(k);
        variables.push(json!({"key": k, "kind": "se2", "value": [x + 0.3, y - 0.2, 0.0]}));
        // Heading observed by a prior (ranges say nothing of it).
        factors.push(
            json!({"type": "prior_se2", "keys": [k], "measurement": [0.0, 0.0, 0.0],
            "sigmas": [1e3, 1e3, 0.1]}),
        );
        for (b, p) in beacons.iter().enumerate() {
            factors.push(json!({"type": "range_se2_point2", "keys": [k, 100 + b],
                "measurement": [(p[0] - x).hypot(p[1] - y)], "sigmas": [0.01]}));
        }
        if k > 0 {
            let [px, py] = truth(k - 1);
            factors.push(json!({"type": "range_se2", "keys": [k - 1, k],
                "measurement": [(x - px).hypot(y - py)], "sigmas": [0.01]}));
        }
    }
    let (status, ack) = post(
        &c,
        &s.url("/v1/sessions/uwb2/batches"),
        &json!({"variables": variables, "factors": factors}),
    )
    .await;
    assert!(status < 300, "{ack}");
    let (status, solved) = post(
        &c,
        &s.url("/v1/sessions/uwb2/optimize?wait=true"),
        &json!({}),
    )
    .await;
    assert_eq!(status, 200, "{solved}");
    let (_, estimate) = get(&c, &s.url("/v1/sessions/uwb2/estimate")).await;
    for k in 0..8 {
        let v = estimate_of(&estimate, k as u64);
        let [x, y] = truth(k);
        assert!(
            (v[0] - x).abs() < 1e-4 && (v[1] - y).abs() < 1e-4,
            "pose {k}: {v:?}"
        );
    }
    s.assert_no_panic();
}
