//! An estimate as the files trajectory and mapping tools read (`estimate?format=…`):
//!
//! - `tum`: `timestamp tx ty tz qx qy qz qw` per pose (evo, rpg_trajectory_evaluation). The
//!   timestamp is the pose's `stamp` when every pose has one; otherwise every line carries its
//!   key instead and a comment line says so, so evo's association never mixes the two.
//! - `kitti`: the 3×4 matrix `[R | t]` row-major per pose, same order (KITTI has no stamps).
//! - `g2o`: the optimised vertices (`VERTEX_SE2`, `VERTEX_SE3:QUAT`, `VERTEX_XY`,
//!   `VERTEX_TRACKXYZ`); the edges are what the client sent, so they are not repeated.
//! - `ply`: ASCII point cloud of pose positions (blue), landmarks (orange) and camera centres
//!   (green), for MeshLab or CloudCompare.
//!
//! Poses are `se2` (z = 0, rotation about z) and `se3`; a window session's keyframes are given
//! here as `se3` with their time as stamp. Numbers are written in Rust's shortest form that
//! reads back to the same `f64`, so an export loses nothing.

use std::fmt::Write;

use nalgebra::{Rotation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use super::wire::VariableValue;
use crate::io::tum;

/// What `estimate?format=` asks for.
#[derive(Clone, Copy, Debug, Default, Deserialize, Serialize, PartialEq, Eq, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum EstimateFormat {
    #[default]
    Json,
    Tum,
    Kitti,
    G2o,
    Ply,
}

impl EstimateFormat {
    /// File extension, also used for the suggested download name.
    pub fn extension(self) -> &'static str {
        match self {
            EstimateFormat::Json => "json",
            EstimateFormat::Tum => "tum",
            EstimateFormat::Kitti => "kitti",
            EstimateFormat::G2o => "g2o",
            EstimateFormat::Ply => "ply",
        }
    }
}

/// A rendered export: the text and how to serve it.
#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct Export {
    pub session: String,
    pub format: EstimateFormat,
    /// The file name a browser should save it under (`<session>.<extension>`).
    pub file_name: String,
    pub body: String,
}

impl Export {
    pub const MEDIA_TYPE: &'static str = "text/plain; charset=utf-8";
}

/// A pose read from a variable's wire value.
struct Pose {
    key: u64,
    stamp: Option<f64>,
    translation: Vector3<f64>,
    rotation: UnitQuaternion<f64>,
}

fn pose_of(v: &VariableValue) -> Option<Pose> {
    let (translation, rotation) = match (&*v.kind, v.value.as_slice()) {
        ("se2", &[x, y, theta]) => (
            Vector3::new(x, y, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), theta),
        ),
        ("se3", &[x, y, z, qx, qy, qz, qw]) => (
            Vector3::new(x, y, z),
            UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(qw, qx, qy, qz)),
        ),
        _ => return None,
    };
    Some(Pose {
        key: v.key,
        stamp: v.stamp,
        translation,
        rotation,
    })
}

/// Renders `variables` (any kinds; each format takes those it can hold) as `format`.
/// `Json` is the estimate itself and is not rendered here.
pub fn render(session: &str, format: EstimateFormat, variables: &[VariableValue]) -> Export {
    let body = match format {
        EstimateFormat::Json => String::new(),
        EstimateFormat::Tum => tum(variables),
        EstimateFormat::Kitti => kitti(variables),
        EstimateFormat::G2o => g2o(variables),
        EstimateFormat::Ply => ply(variables),
    };
    Export {
        session: session.into(),
        format,
        file_name: format!("{session}.{}", format.extension()),
        body,
    }
}

/// The poses in trajectory order: by stamp when every pose has one, else by key.
fn trajectory(variables: &[VariableValue]) -> (Vec<Pose>, bool) {
    let mut poses: Vec<Pose> = variables.iter().filter_map(pose_of).collect();
    let stamped = !poses.is_empty() && poses.iter().all(|p| p.stamp.is_some());
    if stamped {
        poses.sort_by(|a, b| a.stamp.partial_cmp(&b.stamp).expect("stamps are finite"));
    } else {
        poses.sort_by_key(|p| p.key);
    }
    (poses, stamped)
}

fn tum(variables: &[VariableValue]) -> String {
    let (poses, stamped) = trajectory(variables);
    let mut out = String::from(tum::TIMESTAMP_HEADER);
    if !stamped && !poses.is_empty() {
        out.push_str("# not every pose has a stamp: the first column is the variable's key\n");
    }
    for p in &poses {
        let time = match p.stamp {
            Some(s) if stamped => s,
            _ => p.key as f64,
        };
        let (t, q) = (&p.translation, p.rotation.quaternion());
        tum::push_line(&mut out, time, [t.x, t.y, t.z], [q.i, q.j, q.k, q.w]);
    }
    out
}

fn kitti(variables: &[VariableValue]) -> String {
    let (poses, _) = trajectory(variables);
    let mut out = String::new();
    for p in &poses {
        let r = p.rotation.to_rotation_matrix();
        let t = &p.translation;
        let row = |i: usize| format!("{} {} {} {}", r[(i, 0)], r[(i, 1)], r[(i, 2)], t[i]);
        let _ = writeln!(out, "{} {} {}", row(0), row(1), row(2));
    }
    out
}

fn g2o(variables: &[VariableValue]) -> String {
    let mut out = String::new();
    for v in variables {
        let tag = match &*v.kind {
            "se2" => "VERTEX_SE2",
            "se3" => "VERTEX_SE3:QUAT",
            "point2" => "VERTEX_XY",
            "point3" => "VERTEX_TRACKXYZ",
            _ => continue,
        };
        let _ = write!(out, "{tag} {}", v.key);
        for x in &v.value {
            let _ = write!(out, " {x}");
        }
        out.push('\n');
    }
    out
}

/// Colours by what a vertex is, so a viewer tells the trajectory from the map.
const POSE_RGB: [u8; 3] = [40, 90, 220];
const LANDMARK_RGB: [u8; 3] = [240, 140, 20];
const CAMERA_RGB: [u8; 3] = [30, 170, 60];

fn ply(variables: &[VariableValue]) -> String {
    let points: Vec<([f64; 3], [u8; 3])> = variables
        .iter()
        .filter_map(|v| match (&*v.kind, v.value.as_slice()) {
            ("point2", &[x, y]) => Some(([x, y, 0.0], LANDMARK_RGB)),
            ("point3", &[x, y, z]) => Some(([x, y, z], LANDMARK_RGB)),
            // BAL's camera: angle-axis ω and t map world to camera, so its centre is −Rᵀt.
            ("snavely_camera", [w0, w1, w2, t0, t1, t2, ..]) => {
                let r = Rotation3::new(Vector3::new(*w0, *w1, *w2));
                let c = -(r.transpose() * Vector3::new(*t0, *t1, *t2));
                Some(([c.x, c.y, c.z], CAMERA_RGB))
            }
            _ => pose_of(v).map(|p| {
                let t = p.translation;
                ([t.x, t.y, t.z], POSE_RGB)
            }),
        })
        .collect();
    let mut out = format!(
        "ply\nformat ascii 1.0\ncomment factord estimate\nelement vertex {}\n\
         property double x\nproperty double y\nproperty double z\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n",
        points.len()
    );
    for ([x, y, z], [r, g, b]) in points {
        let _ = writeln!(out, "{x} {y} {z} {r} {g} {b}");
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn var(key: u64, kind: &'static str, value: &[f64], stamp: Option<f64>) -> VariableValue {
        VariableValue {
            key,
            kind: kind.into(),
            value: value.into(),
            changed: 0,
            stamp,
        }
    }

    #[test]
    fn tum_uses_stamps_only_when_every_pose_has_one() {
        let theta = std::f64::consts::FRAC_PI_2;
        let stamped = [
            var(2, "se2", &[1.0, 2.0, theta], Some(10.5)),
            var(1, "se2", &[0.0, 0.0, 0.0], Some(10.25)),
            var(9, "point2", &[5.0, 5.0], None),
        ];
        let text = tum(&stamped);
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[1], "10.25 0 0 0 0 0 0 1");
        let fields: Vec<f64> = lines[2].split(' ').map(|f| f.parse().unwrap()).collect();
        assert_eq!(&fields[..4], &[10.5, 1.0, 2.0, 0.0]);
        let half = (theta / 2.0).sin();
        assert!((fields[6] - half).abs() < 1e-15 && (fields[7] - half).abs() < 1e-15);
        assert_eq!(lines.len(), 3, "landmarks are not trajectory lines");

        let partly = [stamped[0].clone(), var(1, "se2", &[0.0, 0.0, 0.0], None)];
        let text = tum(&partly);
        assert!(text
            .lines()
            .nth(1)
            .unwrap()
            .contains("first column is the variable's key"));
        assert!(text.lines().nth(2).unwrap().starts_with("1 "));
    }

    #[test]
    fn numbers_read_back_exactly() {
        let x = 0.1 + 0.2;
        let text = g2o(&[var(7, "se3", &[x, 1e-300, -3.0, 0.0, 0.0, 0.0, 1.0], None)]);
        let fields: Vec<&str> = text.split_whitespace().collect();
        assert_eq!(fields[0], "VERTEX_SE3:QUAT");
        assert_eq!(fields[2].parse::<f64>().unwrap(), x);
        assert_eq!(fields[3].parse::<f64>().unwrap(), 1e-300);
    }

    #[test]
    fn kitti_rows_are_rotation_and_translation() {
        let text = kitti(&[var(0, "se2", &[3.0, 4.0, std::f64::consts::PI], None)]);
        let m: Vec<f64> = text
            .split_whitespace()
            .map(|f| f.parse().unwrap())
            .collect();
        let want = [-1.0, 0.0, 0.0, 3.0, 0.0, -1.0, 0.0, 4.0, 0.0, 0.0, 1.0, 0.0];
        assert!(
            m.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-12),
            "{m:?}"
        );
    }

    #[test]
    fn ply_counts_what_it_holds() {
        let camera = [0.0, 0.0, 0.0, 1.0, 2.0, 3.0, 500.0, 0.0, 0.0];
        let text = ply(&[
            var(0, "snavely_camera", &camera, None),
            var(1, "point3", &[1.0, 1.0, 1.0], None),
        ]);
        assert!(text.contains("element vertex 2\n"));
        assert!(text.contains("\n-1 -2 -3 30 170 60\n"), "{text}");
    }
}
