//! ASCII PLY point clouds (MeshLab, CloudCompare): scene points in grey, camera centres in red.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use nalgebra::Vector3;

use super::IoError;

/// The cloud as PLY text: `points` then `cameras`, one coloured vertex each.
pub fn to_string(points: &[Vector3<f64>], cameras: &[Vector3<f64>]) -> String {
    cloud(points, cameras, false)
}

/// As [`to_string`], with the camera centres joined in order by edges: a trajectory.
pub fn trajectory_to_string(points: &[Vector3<f64>], cameras: &[Vector3<f64>]) -> String {
    cloud(points, cameras, true)
}

fn cloud(points: &[Vector3<f64>], cameras: &[Vector3<f64>], trajectory: bool) -> String {
    let edges = if trajectory {
        cameras.len().saturating_sub(1)
    } else {
        0
    };
    let mut out = format!(
        "ply\nformat ascii 1.0\ncomment factord: {} points (grey), {} camera centres (red){}\nelement vertex {}\nproperty double x\nproperty double y\nproperty double z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n",
        points.len(),
        cameras.len(),
        if trajectory { ", joined in order by edges" } else { "" },
        points.len() + cameras.len()
    );
    if edges > 0 {
        let _ = write!(
            out,
            "element edge {edges}\nproperty int vertex1\nproperty int vertex2\n"
        );
    }
    out.push_str("end_header\n");
    for (list, colour) in [(points, "200 200 200"), (cameras, "255 0 0")] {
        for p in list {
            let _ = writeln!(out, "{} {} {} {colour}", p.x, p.y, p.z);
        }
    }
    for k in 0..edges {
        let first = points.len() + k;
        let _ = writeln!(out, "{first} {}", first + 1);
    }
    out
}

pub fn write(
    path: &Path,
    points: &[Vector3<f64>],
    cameras: &[Vector3<f64>],
) -> Result<(), IoError> {
    save(path, to_string(points, cameras))
}

/// Writes [`trajectory_to_string`].
pub fn write_trajectory(
    path: &Path,
    points: &[Vector3<f64>],
    cameras: &[Vector3<f64>],
) -> Result<(), IoError> {
    save(path, trajectory_to_string(points, cameras))
}

fn save(path: &Path, text: String) -> Result<(), IoError> {
    std::fs::write(path, text).map_err(|source| IoError::Write {
        file: PathBuf::from(path),
        source,
    })
}
