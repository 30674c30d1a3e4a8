//! Two robots walking one 10 m square in their own odometry frames, as the robot-stream tests
//! send them: each robot's batches (its poses as it sees them, odometry between them) and the
//! closures that merge them.

use factord::api::robots::robot_key;
use factord::geometry::Se2;
use serde_json::{json, Value};

pub const INFO: [f64; 6] = [400.0, 0.0, 0.0, 400.0, 0.0, 2500.0];

/// A walk around a 10 m square, `offset` poses into it (1 m apart, 40 around).
pub fn truth(offset: usize, poses: usize) -> Vec<Se2> {
    (0..poses)
        .map(|i| {
            let s = ((i + offset) % 40) as f64;
            let (side, along) = ((s / 10.0).floor(), s % 10.0);
            match side as i64 {
                0 => Se2::new(along, 0.0, 0.0),
                1 => Se2::new(10.0, along, std::f64::consts::FRAC_PI_2),
                2 => Se2::new(10.0 - along, 10.0, std::f64::consts::PI),
                _ => Se2::new(0.0, 10.0 - along, -std::f64::consts::FRAC_PI_2),
            }
        })
        .collect()
}

/// What robot `r` sends for pose `i`: its value in its own odometry frame.
pub fn sent(world: &[Se2], i: usize) -> Se2 {
    world[0].inverse().compose(&world[i])
}

/// Robot `r`'s poses `range` and the odometry between them, as one batch.
pub fn robot_batch(r: char, world: &[Se2], range: std::ops::Range<usize>) -> Value {
    let variables: Vec<Value> = range
        .clone()
        .map(|i| json!({"key": robot_key(r, i as u64), "kind": "se2", "value": sent(world, i).to_array()}))
        .collect();
    let factors: Vec<Value> = range
        .filter(|&i| i > 0)
        .map(|i| {
            json!({"type": "between_se2", "keys": [robot_key(r, i as u64 - 1), robot_key(r, i as u64)],
                   "measurement": world[i - 1].between(&world[i]).to_array(), "information": INFO})
        })
        .collect();
    json!({"variables": variables, "factors": factors})
}

/// A closure between pose `i` of robot a and pose `j` of robot b.
pub fn closure(a: &[Se2], i: usize, b: &[Se2], j: usize) -> Value {
    json!({"type": "between_se2", "keys": [robot_key('a', i as u64), robot_key('b', j as u64)],
           "measurement": a[i].between(&b[j]).to_array(), "information": INFO})
}
