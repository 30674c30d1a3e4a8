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
    let factors: Vec<Value> = bal
        .problem
        .factors()
        .iter()
        .map(|f| {
            let z = f
                .factor
                .as_any()
                .downcast_ref::<factord::factors::ReprojectionSnavely>()
                .unwrap()
                .observed;
            json!({"type": "reprojection_snavely", "keys": f.factor.keys(), "measurement": [z.x, z.y], "sigmas": [1.0, 1.0]})
        })
        .collect();
    let batches = factors
        .chunks(per_batch)
        .map(|chunk| json!({ "factors": chunk }))
        .collect();
    (json!({ "variables": variables }), batches)
}
