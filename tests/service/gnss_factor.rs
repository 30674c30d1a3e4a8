//! `gnss_position_se3` over the wire, against the real server: a drifting odometry chain of SE(3)
//! poses is pulled back onto GNSS fixes, the same over HTTP and over zenoh, and a fix with the
//! wrong number of coordinates is refused naming the field.

use crate::common;

use common::server::{client, create, get, post, zenoh_get, zenoh_peer, TestServer};
use factord::geometry::{so3, Se3};
use nalgebra::Vector3;
use serde_json::{json, Value};

const POSES: usize = 20;
const GNSS_SIGMA: f64 = 0.1;

fn se3_json(x: &Se3) -> Value {
    let q = x.rotation.quaternion();
    let t = x.translation;
    json!([t.x, t.y, t.z, q.i, q.j, q.k, q.w])
}

/// The true path: 1 m steps turning 0.1 rad left each; odometry measures each step 3 % too long
/// and 0.01 rad too far left (dead reckoning ends 1.5 m off); GNSS measures
/// every true position. Initial values are the dead-reckoned poses. Returns the batch, the true
/// positions and the dead-reckoned ones.
fn drifted_batch() -> (Value, Vec<Vector3<f64>>, Vec<Vector3<f64>>) {
    let (step, measured) = steps();
    let (mut truth, mut dead) = (vec![Se3::identity()], vec![Se3::identity()]);
    for k in 1..POSES {
        truth.push(truth[k - 1].compose(&step));
        dead.push(dead[k - 1].compose(&measured));
    }
    let variables: Vec<Value> = (0..POSES)
        .map(|k| json!({"key": k, "kind": "se3", "value": se3_json(&dead[k])}))
        .collect();
    let mut factors: Vec<Value> = (1..POSES)
        .map(|k| {
            json!({"type": "between_se3", "keys": [k - 1, k], "measurement": se3_json(&measured),
                   "sigmas": [0.1, 0.1, 0.1, 0.05, 0.05, 0.05]})
        })
        .collect();
    for (k, x) in truth.iter().enumerate() {
        let p = x.translation;
        factors.push(
            json!({"type": "gnss_position_se3", "keys": [k], "measurement": [p.x, p.y, p.z],
                            "sigmas": [GNSS_SIGMA, GNSS_SIGMA, GNSS_SIGMA]}),
        );
    }
    let positions = |v: &[Se3]| v.iter().map(|x| x.translation).collect();
    (
        json!({"variables": variables, "factors": factors}),
        positions(&truth),
        positions(&dead),
    )
}

/// Σ |e|² over the odometry factors at the true poses, whitened by their sigmas: every step's
/// residual is the same, `[t_E; Log(R_E)]` with `E = Z⁻¹ S` (Z measured, S the true step).
fn odometry_cost_at_truth() -> f64 {
    let (step, measured) = steps();
    let e = measured.between(&step);
    let (t, r) = (e.translation / 0.1, so3::log(&e.rotation) / 0.05);
    (POSES - 1) as f64 * (t.norm_squared() + r.norm_squared())
}

/// The true step and the one odometry measures.
fn steps() -> (Se3, Se3) {
    let step = Se3::new(
        so3::exp(&Vector3::new(0.0, 0.0, 0.1)),
        Vector3::new(1.0, 0.0, 0.0),
    );
    let measured = Se3::new(
        so3::exp(&Vector3::new(0.0, 0.0, 0.11)),
        Vector3::new(1.03, 0.0, 0.0),
    );
    (step, measured)
}

fn positions(estimate: &Value) -> Vec<Vector3<f64>> {
    let mut vars = estimate["variables"].as_array().expect("variables").clone();
    vars.sort_by_key(|v| v["key"].as_u64());
    vars.iter()
        .map(|v| {
            let x: Vec<f64> = serde_json::from_value(v["value"].clone()).expect("numbers");
            Vector3::new(x[0], x[1], x[2])
        })
        .collect()
}

fn max_distance(a: &[Vector3<f64>], b: &[Vector3<f64>]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).norm())
        .fold(0.0, f64::max)
}

/// A fix of two numbers: refused whole, naming the measurement.
fn short_fix() -> Value {
    json!({"factors": [{"type": "gnss_position_se3", "keys": [0], "measurement": [1.0, 2.0],
                        "sigmas": [1, 1, 1]}]})
}

#[tokio::test(flavor = "multi_thread")]
async fn gnss_fixes_correct_a_drifting_chain_over_http_and_zenoh() {
    let s = TestServer::start(&[]);
    let c = client();
    let (batch, truth, dead) = drifted_batch();
    let drift = max_distance(&dead, &truth);

    // HTTP.
    create(
        &c,
        &s,
        &json!({"session": "h", "kind": "pose_graph_3d", "auto_optimize": {"policy": "manual"}}),
    )
    .await;
    let (status, ack) = post(&c, &s.url("/v1/sessions/h/batches"), &batch).await;
    assert_eq!(status, 200, "{ack}");
    let (status, done) = post(&c, &s.url("/v1/sessions/h/optimize?wait=true"), &json!({})).await;
    assert_eq!(status, 200, "{done}");
    let (status, estimate) = get(&c, &s.url("/v1/sessions/h/estimate")).await;
    assert_eq!(status, 200, "{estimate}");
    let over_http = positions(&estimate);

    // Zenoh rpc, the same batch in another session.
    let z = zenoh_peer(&s.zenoh).await;
    let rpc = |command: Value| {
        let z = &z;
        async move { zenoh_get(z, "factord/rpc", Some(&command)).await }
    };
    rpc(
        json!({"op": "create_session", "session": "z", "kind": "pose_graph_3d",
               "auto_optimize": {"policy": "manual"}}),
    )
    .await
    .expect("created");
    rpc(json!({"op": "apply_batch", "session": "z", "batch": batch}))
        .await
        .expect("applied");
    rpc(json!({"op": "optimize", "session": "z", "wait": true}))
        .await
        .expect("optimised");
    let estimate = rpc(json!({"op": "get_estimate", "session": "z"}))
        .await
        .expect("estimate");
    let over_zenoh = positions(&estimate);

    // A bound that follows from optimality: the estimate's cost is at most the cost of the true
    // poses, which only the odometry pays (the fixes are exact there); the fixes' share of the
    // estimate's cost, Σ|t_k − p_k|²/σ², is below that, so every |t_k − p_k| ≤ σ √cost(truth).
    let bound = GNSS_SIGMA * odometry_cost_at_truth().sqrt();
    let fit = max_distance(&over_http, &truth);
    println!(
        "dead reckoning off by up to {drift:.3} m; estimate off the fixes by up to {fit:.4} m \
         (bound {bound:.4} m)"
    );
    assert!(drift > 1.0, "the chain should drift: {drift}");
    assert!(
        bound < drift / 5.0,
        "the bound should say something: {bound} vs {drift}"
    );
    assert!(
        fit <= bound,
        "estimate off the GNSS fixes by {fit} m > {bound} m"
    );
    assert!(
        max_distance(&over_http, &over_zenoh) < 1e-9,
        "HTTP and zenoh sessions disagree:\n{over_http:?}\n{over_zenoh:?}"
    );

    // A wrong measurement length: 400 naming the field, both ways.
    let (status, error) = post(&c, &s.url("/v1/sessions/h/batches"), &short_fix()).await;
    assert_eq!(status, 400, "{error}");
    assert_eq!(error["error"]["code"], "wrong_dimension", "{error}");
    assert_eq!(error["error"]["field"], "factors[0].measurement", "{error}");
    assert!(
        error["error"]["message"]
            .as_str()
            .unwrap_or("")
            .contains("gnss_position_se3"),
        "{error}"
    );
    let error = rpc(json!({"op": "apply_batch", "session": "z", "batch": short_fix()}))
        .await
        .expect_err("refused");
    assert_eq!(error["error"]["status"], 400, "{error}");
    assert_eq!(error["error"]["field"], "factors[0].measurement", "{error}");
    z.close().await.expect("zenoh closes");
    s.assert_no_panic();
}
