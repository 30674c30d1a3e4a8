//! The session's graph as a `visualization_msgs/MarkerArray`, what rviz's and Foxglove's
//! "MarkerArray" displays draw as published, in the binding's map frame. Four markers, each
//! replacing its previous self (same `ns` and `id`, action ADD):
//!
//! - `poses`: the keyframes' positions (POINTS, white);
//! - `odometry`: edges between consecutive keyframes (LINE_LIST, grey);
//! - `loop_closures`: the other pose-to-pose edges (LINE_LIST), coloured by their χ² at the
//!   estimate (the whitened error's squared norm; 6 degrees of freedom): green up to χ²₆'s 95 %
//!   quantile, red from its 99.9 % (a closure the optimum does not agree with: wrong, or
//!   outweighed), blended between; grey while a solve holds the problem (χ² unknown);
//! - `landmarks`: the point landmarks (SPHERE_LIST, blue).
//!
//! The message types are Jazzy's, fields in their `.msg` order (`idl/visualization_msgs`),
//! which is the CDR order; `MARKER_ARRAY`'s hash is recomputed from those files by `type_hash`.

use std::collections::HashMap;

use serde::{Deserialize, Serialize};

use super::messages::{Header, Point, Pose, Time, Vector3};
use crate::api::wire::Graph;

/// `std_msgs/ColorRGBA`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ColorRgba {
    pub r: f32,
    pub g: f32,
    pub b: f32,
    pub a: f32,
}

/// `builtin_interfaces/Duration`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Duration {
    pub sec: i32,
    pub nanosec: u32,
}

/// `sensor_msgs/CompressedImage` (a marker's texture; unused, empty).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CompressedImage {
    pub header: Header,
    pub format: String,
    pub data: Vec<u8>,
}

/// `visualization_msgs/UVCoordinate`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct UvCoordinate {
    pub u: f32,
    pub v: f32,
}

/// `visualization_msgs/MeshFile` (unused, empty).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MeshFile {
    pub filename: String,
    pub data: Vec<u8>,
}

/// `visualization_msgs/Marker` (Jazzy: with texture, UV coordinates and mesh file).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Marker {
    pub header: Header,
    pub ns: String,
    pub id: i32,
    #[serde(rename = "type")]
    pub marker_type: i32,
    pub action: i32,
    pub pose: Pose,
    pub scale: Vector3,
    pub color: ColorRgba,
    pub lifetime: Duration,
    pub frame_locked: bool,
    pub points: Vec<Point>,
    pub colors: Vec<ColorRgba>,
    pub texture_resource: String,
    pub texture: CompressedImage,
    pub uv_coordinates: Vec<UvCoordinate>,
    pub text: String,
    pub mesh_resource: String,
    pub mesh_file: MeshFile,
    pub mesh_use_embedded_materials: bool,
}

/// `visualization_msgs/MarkerArray`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MarkerArray {
    pub markers: Vec<Marker>,
}

/// `Marker.type` values.
const LINE_LIST: i32 = 5;
const SPHERE_LIST: i32 = 7;
const POINTS: i32 = 8;

/// χ²₆ quantiles: 95 % (all green up to it) and 99.9 % (all red from it).
const CHI2_GREEN: f64 = 12.59;
const CHI2_RED: f64 = 22.46;

const WHITE: ColorRgba = rgba(1.0, 1.0, 1.0);
const GREY: ColorRgba = rgba(0.6, 0.6, 0.6);
const BLUE: ColorRgba = rgba(0.2, 0.4, 1.0);

const fn rgba(r: f32, g: f32, b: f32) -> ColorRgba {
    ColorRgba { r, g, b, a: 1.0 }
}

/// A loop closure's colour by its χ² (grey when unknown).
pub fn closure_colour(chi2: Option<f64>) -> ColorRgba {
    let Some(chi2) = chi2 else { return GREY };
    let red = ((chi2 - CHI2_GREEN) / (CHI2_RED - CHI2_GREEN)).clamp(0.0, 1.0) as f32;
    rgba(red, 1.0 - red, 0.0)
}

/// The markers of `graph`, stamped `stamp` in `frame`.
pub fn graph_markers(graph: &Graph, frame: &str, stamp: Time) -> MarkerArray {
    let header = Header {
        stamp,
        frame_id: frame.into(),
    };
    let marker = |ns: &str, marker_type, size: f64, color| Marker {
        header: header.clone(),
        ns: ns.into(),
        marker_type,
        scale: Vector3 {
            x: size,
            y: size,
            z: size,
        },
        color,
        ..Marker::default()
    };
    let point = |p: &[f64; 3]| Point {
        x: p[0],
        y: p[1],
        z: p[2],
    };
    let at: HashMap<u64, Point> = graph
        .poses
        .iter()
        .map(|v| (v.key, point(&v.position)))
        .collect();

    let mut poses = marker("poses", POINTS, 0.1, WHITE);
    poses.points = graph.poses.iter().map(|v| point(&v.position)).collect();
    let mut odometry = marker("odometry", LINE_LIST, 0.03, GREY);
    let mut closures = marker("loop_closures", LINE_LIST, 0.05, GREY);
    for (i, &[a, b]) in graph.edges.iter().enumerate() {
        let (Some(&pa), Some(&pb)) = (at.get(&a), at.get(&b)) else {
            continue;
        };
        if a.abs_diff(b) == 1 {
            odometry.points.extend([pa, pb]);
        } else {
            let colour = closure_colour(graph.edge_chi2.get(i).copied().flatten());
            closures.points.extend([pa, pb]);
            closures.colors.extend([colour, colour]);
        }
    }
    let mut landmarks = marker("landmarks", SPHERE_LIST, 0.3, BLUE);
    landmarks.points = graph.points.iter().map(|v| point(&v.position)).collect();
    MarkerArray {
        markers: vec![poses, odometry, closures, landmarks],
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::api::wire::DrawnVariable;
    use crate::transport::ros2::cdr_codec;
    use crate::transport::ros2::messages::MARKER_ARRAY;

    fn drawn(key: u64, x: f64) -> DrawnVariable {
        DrawnVariable {
            key,
            position: [x, 0.0, 0.0],
            initial: [x, 0.0, 0.0],
        }
    }

    fn graph() -> Graph {
        Graph {
            session: "s".into(),
            kind: "pose_graph_3d".into(),
            sequence: 3,
            dimension: 3,
            poses: (0..4).map(|k| drawn(k, k as f64)).collect(),
            points: vec![drawn(u64::from(b'l') << 56, 9.0)],
            edges: vec![[0, 1], [1, 2], [2, 3], [0, 3], [1, 3]],
            edge_chi2: vec![Some(1.0), Some(1.0), Some(1.0), Some(3.0), Some(400.0)],
        }
    }

    #[test]
    fn odometry_closures_and_landmarks_are_markers_of_their_own() {
        let m = graph_markers(&graph(), "map", Time { sec: 5, nanosec: 0 });
        let ns: Vec<_> = m.markers.iter().map(|m| m.ns.as_str()).collect();
        assert_eq!(ns, ["poses", "odometry", "loop_closures", "landmarks"]);
        assert_eq!(m.markers[0].points.len(), 4);
        assert_eq!(m.markers[1].points.len(), 6);
        let closures = &m.markers[2];
        assert_eq!(closures.points.len(), 4);
        assert_eq!(closures.colors.len(), 4);
        assert_eq!(closures.colors[0], rgba(0.0, 1.0, 0.0), "χ² 3: agreed");
        assert_eq!(closures.colors[2], rgba(1.0, 0.0, 0.0), "χ² 400: refused");
        assert_eq!(closure_colour(None), GREY);
        assert_eq!(m.markers[3].points[0].x, 9.0);
        assert!(m.markers.iter().all(|m| m.header.frame_id == "map"));
    }

    #[test]
    fn the_cdr_round_trips() {
        let m = graph_markers(&graph(), "map", Time { sec: 5, nanosec: 7 });
        let bytes = cdr_codec::encode(&m);
        let back: MarkerArray = cdr_codec::decode(&bytes, MARKER_ARRAY.name).unwrap();
        assert_eq!(back, m);
    }
}
