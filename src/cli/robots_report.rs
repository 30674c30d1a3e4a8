//! `factord solve` on a file of several robots: its poses keyed by robot (GTSAM's
//! `Symbol('a', i)`, `('a' << 56) | i`), each robot's values in its own odometry frame, closures
//! between robots as ordinary edges. The solve itself needs nothing of robots (the chordal start
//! reads only the measurements, so the frames the values came in do not matter); this reports
//! each robot's view back: its poses and `map ← odom`, the transform that takes its first pose
//! as the file gives it onto the solved one (the map is the frame of the lowest key's robot,
//! whose first pose stays where the file has it).

use std::collections::BTreeMap;

use serde::Serialize;

use factord::api::robots::robot_of_key;
use factord::problem::Values;
use factord::variables::frame::Frame;

/// One robot of a solved file.
#[derive(Debug, Serialize)]
pub struct RobotView {
    pub robot: char,
    pub poses: usize,
    /// Its lowest-keyed pose, the one `map_from_odom` is taken at.
    pub first_key: u64,
    /// `[x, y, θ]` or `[x, y, z, qx, qy, qz, qw]`.
    pub map_from_odom: Vec<f64>,
}

/// Every robot of `solved` (poses whose keys name one), when there are at least two; else
/// nothing (a file of one robot, or of plain ids).
pub fn robot_views(initial: &Values, solved: &Values) -> Vec<RobotView> {
    let mut first: BTreeMap<char, (u64, usize)> = BTreeMap::new();
    for (i, &key) in solved.keys().iter().enumerate() {
        let kind = solved.variable(i).kind();
        let Some(robot) = robot_of_key(key).filter(|_| kind == "se2" || kind == "se3") else {
            continue;
        };
        let entry = first.entry(robot).or_insert((key, 0));
        entry.0 = entry.0.min(key);
        entry.1 += 1;
    }
    if first.len() < 2 {
        return Vec::new();
    }
    first
        .into_iter()
        .filter_map(|(robot, (first_key, poses))| {
            let (Some(given), Some(found)) = (initial.get(first_key), solved.get(first_key)) else {
                return None;
            };
            let frame = Frame::between_poses(found, given)?;
            Some(RobotView {
                robot,
                poses,
                first_key,
                map_from_odom: frame.to_wire(),
            })
        })
        .collect()
}

/// The console lines: one per robot.
pub fn report(views: &[RobotView]) -> String {
    let mut out = String::new();
    for v in views {
        let t: Vec<String> = v.map_from_odom.iter().map(|x| format!("{x:.6}")).collect();
        out.push_str(&format!(
            "robot {}: {} poses, map ← odom [{}]\n",
            v.robot,
            v.poses,
            t.join(", ")
        ));
    }
    out
}
