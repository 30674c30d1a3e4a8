//! A BAL problem as a bundle_adjustment session's batches: its cameras and points, then its
//! observations as reprojection factors.

use std::collections::{BTreeMap, BTreeSet, HashSet};

use serde_json::{json, Value};

/// The variables batch, then the factors in batches of `per_batch`.
pub fn batches(text: &str, per_batch: usize) -> (Value, Vec<Value>) {
    let bal = factord::io::bal::parse(std::path::Path::new("bal"), text).unwrap();
    let values = &bal.problem.values;
    let variables: Vec<Value> = values
        .keys()
        .iter()
        .map(|&k| {
            let v = values.get(k).unwrap();
            json!({"key": k, "kind": v.kind(), "value": factord::api::catalogue::encode_variable(v)})
        })
        .collect();
    let factors: Vec<Value> = observations(&bal.problem).iter().map(factor).collect();
    let batches = factors
        .chunks(per_batch)
        .map(|chunk| json!({ "factors": chunk }))
        .collect();
    (json!({ "variables": variables }), batches)
}

/// A BAL problem's observations: (camera key, point key, pixel).
pub fn observations(problem: &factord::problem::Problem) -> Vec<(u64, u64, [f64; 2])> {
    problem
        .factors()
        .iter()
        .map(|f| {
            let z = f
                .factor
                .as_any()
                .downcast_ref::<factord::factors::ReprojectionSnavely>()
                .unwrap()
                .observed;
            (f.factor.keys()[0], f.factor.keys()[1], [z.x, z.y])
        })
        .collect()
}

/// An observation as a session's reprojection factor (σ 1 pixel).
pub fn factor(&(camera, point, z): &(u64, u64, [f64; 2])) -> Value {
    json!({"type": "reprojection_snavely", "keys": [camera, point], "measurement": z, "sigmas": [1.0, 1.0]})
}

/// A stream: batches of `cameras_per_batch` cameras in index order; a point enters (with the file's value) once
/// two sent cameras see it, with every observation of it by sent cameras; later observations
/// arrive with their cameras.
pub fn camera_batches(text: &str, cameras_per_batch: usize) -> Vec<Value> {
    let bal = factord::io::bal::parse(std::path::Path::new("bal"), text).unwrap();
    let problem = &bal.problem;
    let value = |key: u64| {
        let v = problem.values.get(key).unwrap();
        json!({"key": key, "kind": v.kind(), "value": factord::api::catalogue::encode_variable(v)})
    };
    let observations = observations(problem);
    let cameras = problem
        .values
        .keys()
        .iter()
        .filter(|&&k| problem.values.get(k).unwrap().kind() == "snavely_camera")
        .count() as u64;
    let mut entered = HashSet::new();
    let mut batches = Vec::new();
    for first in (0..cameras).step_by(cameras_per_batch) {
        let sent = first + cameras_per_batch as u64;
        let mut variables: Vec<Value> = (first..sent.min(cameras)).map(value).collect();
        let mut seen_by: BTreeMap<u64, Vec<u64>> = BTreeMap::new();
        for &(camera, point, _) in &observations {
            if camera < sent {
                seen_by.entry(point).or_default().push(camera);
            }
        }
        let entering: BTreeSet<u64> = seen_by
            .iter()
            .filter(|(point, cams)| cams.len() >= 2 && !entered.contains(*point))
            .map(|(&point, _)| point)
            .collect();
        variables.extend(entering.iter().copied().map(value));
        let factors: Vec<Value> = observations
            .iter()
            .filter(|(camera, point, _)| {
                *camera < sent
                    && (entering.contains(point) || (*camera >= first && entered.contains(point)))
            })
            .map(factor)
            .collect();
        entered.extend(entering);
        batches.push(json!({"variables": variables, "factors": factors}));
    }
    // Every BAL point is seen twice or more: the stream ends at the whole problem.
    assert_eq!(entered.len() as u64, problem.values.len() as u64 - cameras);
    batches
}
