//! A BAL problem as a bundle_adjustment session's batches: its cameras and points, then its
//! observations as reprojection factors.

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
