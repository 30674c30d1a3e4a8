//! ASCII PLY point clouds (MeshLab, CloudCompare): scene points in grey, camera centres in red.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use nalgebra::Vector3;

use super::IoError;

/// The cloud as PLY text: `points` then `cameras`, one coloured vertex each.
pub fn to_string(points: &[Vector3<f64>], cameras: &[Vector3<f64>]) -> String {
    let mut out = format!(
        "ply\nformat ascii 1.0\ncomment factord: {} points (grey), {} camera centres (red)\nelement vertex {}\nproperty double x\nproperty double y\nproperty double z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n",
        points.len(),
        cameras.len(),
        points.len() + cameras.len()
    );
    for (list, colour) in [(points, "200 200 200"), (cameras, "255 0 0")] {
        for p in list {
            let _ = writeln!(out, "{} {} {} {colour}", p.x, p.y, p.z);
        }
    }
    out
}

pub fn write(
    path: &Path,
    points: &[Vector3<f64>],
    cameras: &[Vector3<f64>],
) -> Result<(), IoError> {
    std::fs::write(path, to_string(points, cameras)).map_err(|source| IoError::Write {
        file: PathBuf::from(path),
        source,
    })
}
