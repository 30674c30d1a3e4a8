//! Batches for a GTSAM landmark text file (`victoria_park.txt`), in the stream order of
//! `isam2_landmarks.py`: batch k holds pose k (a value only for the first pose; the server
//! predicts the others from their odometry), the odometry that ends at k, the landmarks first
//! seen from k (no value: predicted from that sighting) and every sighting from k. Built from
//! factord's own reading of the file, so the noise is the one the batch solve uses.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use serde_json::{json, Value};

use factord::factors::{BearingRangeSe2, BetweenSe2};
use factord::io::parse_text;

/// Whether `text` is GTSAM's landmark format.
pub fn is_gtsam_text(text: &str) -> bool {
    text.split_whitespace()
        .next()
        .is_some_and(|t| t == "ODOMETRY" || t == "LANDMARK")
}

pub fn batches(text: &str, path: &str) -> Vec<Value> {
    let graph = parse_text(text, Path::new(path), None).expect("the file parses");
    let mut steps: BTreeMap<u64, (Vec<Value>, Vec<Value>)> = BTreeMap::new();
    let mut landmarks_seen = BTreeSet::new();
    // Every pose is a step, also one that nothing ends at (the first).
    let values = &graph.problem.values;
    for v in 0..values.len() {
        if values.variable(v).kind() == "se2" {
            steps.entry(values.key(v)).or_default();
        }
    }
    for f in graph.problem.factors() {
        let keys = f.factor.keys();
        let info = f.sqrt_information.information();
        let information: Vec<f64> = info.transpose().iter().copied().collect(); // row-major
        let any = f.factor.as_any();
        let (step, factor, new_landmark) = if let Some(b) = any.downcast_ref::<BetweenSe2>() {
            let z = b.measurement;
            let factor = json!({"type": "between_se2", "keys": keys,
                "measurement": [z.x, z.y, z.theta], "information": information});
            (keys[0].max(keys[1]), factor, None)
        } else if let Some(s) = any.downcast_ref::<BearingRangeSe2>() {
            let factor = json!({"type": "bearing_range_se2", "keys": keys,
                "measurement": [s.bearing, s.range], "information": information});
            let new = landmarks_seen.insert(keys[1]).then_some(keys[1]);
            (keys[0], factor, new)
        } else {
            panic!("unexpected factor {}", f.factor.name());
        };
        let entry = steps.entry(step).or_default();
        entry.1.push(factor);
        if let Some(l) = new_landmark {
            entry.0.push(json!({"key": l, "kind": "point2"}));
        }
    }
    let first = *steps.keys().next().expect("a pose");
    steps
        .into_iter()
        .map(|(k, (landmarks, factors))| {
            let pose = if k == first {
                json!({"key": k, "kind": "se2", "value": [0.0, 0.0, 0.0]})
            } else {
                json!({"key": k, "kind": "se2"})
            };
            let mut variables = vec![pose];
            variables.extend(landmarks);
            json!({"variables": variables, "factors": factors})
        })
        .collect()
}
