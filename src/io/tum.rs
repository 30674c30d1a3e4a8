//! TUM trajectories: `timestamp tx ty tz qx qy qz qw` per line (w last). The vertex id is used as
//! the timestamp; 2D poses are written in the z = 0 plane with a yaw quaternion.

use std::fmt::Write as _;
use std::path::Path;

use nalgebra::{UnitQuaternion, Vector3};

use super::{IoError, PoseGraph};
use crate::geometry::{Se2, Se3};

pub fn to_string(graph: &PoseGraph) -> String {
    let mut out = String::new();
    for &key in &graph.vertex_order {
        let values = &graph.problem.values;
        let (t, q) = if let Some(p) = values.get_as::<Se2>(key) {
            (
                Vector3::new(p.x, p.y, 0.0),
                UnitQuaternion::from_euler_angles(0.0, 0.0, p.theta),
            )
        } else if let Some(p) = values.get_as::<Se3>(key) {
            (p.translation, p.rotation)
        } else {
            continue;
        };
        let _ = writeln!(
            out,
            "{key} {} {} {} {} {} {} {}",
            t.x, t.y, t.z, q.i, q.j, q.k, q.w
        );
    }
    out
}

pub fn write(graph: &PoseGraph, path: &Path) -> Result<(), IoError> {
    std::fs::write(path, to_string(graph)).map_err(|source| IoError::Write {
        file: path.to_path_buf(),
        source,
    })
}
