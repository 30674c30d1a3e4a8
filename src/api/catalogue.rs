//! What a session may contain, by name: variable kinds with their wire encoding, factor types with
//! their decoders, and session kinds as sets of both.
//!
//! The session layer only ever goes through this table, so a new kind of problem (bundle
//! adjustment, sliding-window fusion) is a new entry here plus its variables and factors — the
//! session, the worker pool and the transports do not change.
//!
//! Wire encodings (all numbers are JSON numbers, angles in radians):
//! - `se2`: `[x, y, θ]`.
//! - `se3`: `[x, y, z, qx, qy, qz, qw]` (g2o order); the quaternion must have unit norm within
//!   1e-3 and is normalised.
//! - `snavely_camera`: BAL's nine parameters `[rx, ry, rz, tx, ty, tz, f, k1, k2]` (angle-axis).
//! - `point3`: `[x, y, z]`; `reprojection_snavely` measures the pixel `[x, y]` (BAL convention).
//! - Factor measurements use the same encoding as the variable they relate; information matrices
//!   are in the factor's residual order (`between_se3`: translation then rotation angle, GTSAM's
//!   convention, not g2o's half-angle).

use nalgebra::{Quaternion, UnitQuaternion, Vector2, Vector3};

use crate::factors::{BetweenSe2, BetweenSe3, Factor, PriorSe2, PriorSe3, ReprojectionSnavely};
use crate::geometry::{wrap_angle, Point3, Se2, Se3, SnavelyCamera};
use crate::problem::{Gauge, Key, Variable};
use crate::solver::SolverOptions;

/// Builds a variable from its wire encoding (length already checked), or says why not.
pub type DecodeVariable = fn(&[f64]) -> Result<Box<dyn Variable>, String>;
/// Builds a factor from its keys and measurement (lengths already checked), or says why not.
pub type BuildFactor = fn(&[Key], &[f64]) -> Result<Box<dyn Factor>, String>;

/// How one variable kind travels on the wire.
pub struct VariableCodec {
    pub kind: &'static str,
    /// Number of values in the wire encoding.
    pub len: usize,
    pub decode: DecodeVariable,
    pub encode: fn(&dyn Variable) -> Vec<f64>,
    /// How the web view draws it.
    pub shape: Shape,
}

/// What a variable is when drawn: a pose of the trajectory or a landmark of a point cloud.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Shape {
    Pose,
    Landmark,
}

/// How one factor type is built from its wire form.
pub struct FactorCodec {
    pub name: &'static str,
    /// Kinds of the variables it connects, in key order.
    pub variable_kinds: &'static [&'static str],
    pub measurement_len: usize,
    pub residual_dim: usize,
    pub build: BuildFactor,
}

/// A kind of session: which variables and factors it accepts, and how it is solved by default.
pub struct SessionKind {
    pub name: &'static str,
    pub description: &'static str,
    pub variable_kinds: &'static [&'static str],
    pub factor_types: &'static [&'static str],
    pub gauge: Gauge,
    /// Variable kinds the linear solver eliminates first (Schur complement).
    pub eliminate: &'static [&'static str],
    /// Options when the client gives none.
    pub default_options: fn() -> SolverOptions,
}

/// The kind fed with fusion messages (`session::fusion`) instead of variables and factors.
pub const SLIDING_WINDOW: &str = "sliding_window";

/// Gauss-Newton: what the window runs at every keyframe (see `fusion::window`).
fn sliding_window_options() -> SolverOptions {
    crate::fusion::window::WindowOptions::default().solver
}

pub const SESSION_KINDS: &[SessionKind] = &[
    SessionKind {
        name: "pose_graph_2d",
        description: "SE(2) poses with relative-pose and prior factors",
        variable_kinds: &["se2"],
        factor_types: &["between_se2", "prior_se2"],
        gauge: Gauge::AnchorComponents,
        eliminate: &[],
        default_options: SolverOptions::default,
    },
    SessionKind {
        name: "pose_graph_3d",
        description: "SE(3) poses with relative-pose and prior factors",
        variable_kinds: &["se3"],
        factor_types: &["between_se3", "prior_se3"],
        gauge: Gauge::AnchorComponents,
        eliminate: &[],
        default_options: SolverOptions::default,
    },
    SessionKind {
        name: "bundle_adjustment",
        description: "BAL (Snavely) cameras and 3D points with reprojection factors; the gauge is left to LM's damping",
        variable_kinds: &["snavely_camera", "point3"],
        factor_types: &["reprojection_snavely"],
        gauge: Gauge::Free,
        eliminate: &["point3"],
        default_options: SolverOptions::bundle_adjustment,
    },
    SessionKind {
        name: SLIDING_WINDOW,
        description: "15-dof navigation states in a window of N keyframes, fed with IMU samples, keyframes, relative poses and priors (POST …/fusion, zenoh in/fusion); publishes out/state and out/window",
        // Fed with fusion messages, not batches: no batch codecs (the window builds its
        // nav_state variables and IMU, relative-pose, prior and marginal factors itself).
        variable_kinds: &[],
        factor_types: &[],
        gauge: Gauge::AnchorComponents,
        eliminate: &[],
        default_options: sliding_window_options,
    },
];

const VARIABLES: &[VariableCodec] = &[
    VariableCodec {
        kind: "se2",
        len: 3,
        decode: |v| Ok(Box::new(Se2::new(v[0], v[1], wrap_angle(v[2])))),
        encode: |v| encode_as::<Se2>(v, |p| p.to_array().to_vec()),
        shape: Shape::Pose,
    },
    VariableCodec {
        kind: "se3",
        len: 7,
        decode: |v| Ok(Box::new(decode_se3(v)?)),
        encode: |v| {
            encode_as::<Se3>(v, |p| {
                let q = p.rotation.quaternion();
                let t = p.translation;
                vec![t.x, t.y, t.z, q.i, q.j, q.k, q.w]
            })
        },
        shape: Shape::Pose,
    },
    VariableCodec {
        kind: "snavely_camera",
        len: 9,
        decode: |v| {
            let p: [f64; 9] = v.try_into().expect("length checked");
            Ok(Box::new(SnavelyCamera::from_bal(&p)))
        },
        encode: |v| encode_as::<SnavelyCamera>(v, |c| c.to_bal().to_vec()),
        shape: Shape::Pose,
    },
    VariableCodec {
        kind: "point3",
        len: 3,
        decode: |v| Ok(Box::new(Point3(Vector3::new(v[0], v[1], v[2])))),
        encode: |v| encode_as::<Point3>(v, |p| p.0.iter().copied().collect()),
        shape: Shape::Landmark,
    },
];

const FACTORS: &[FactorCodec] = &[
    FactorCodec {
        name: "between_se2",
        variable_kinds: &["se2", "se2"],
        measurement_len: 3,
        residual_dim: 3,
        build: |k, m| {
            Ok(Box::new(BetweenSe2::new(
                k[0],
                k[1],
                Se2::new(m[0], m[1], wrap_angle(m[2])),
            )))
        },
    },
    FactorCodec {
        name: "prior_se2",
        variable_kinds: &["se2"],
        measurement_len: 3,
        residual_dim: 3,
        build: |k, m| {
            Ok(Box::new(PriorSe2::new(
                k[0],
                Se2::new(m[0], m[1], wrap_angle(m[2])),
            )))
        },
    },
    FactorCodec {
        name: "between_se3",
        variable_kinds: &["se3", "se3"],
        measurement_len: 7,
        residual_dim: 6,
        build: |k, m| Ok(Box::new(BetweenSe3::new(k[0], k[1], decode_se3(m)?))),
    },
    FactorCodec {
        name: "prior_se3",
        variable_kinds: &["se3"],
        measurement_len: 7,
        residual_dim: 6,
        build: |k, m| Ok(Box::new(PriorSe3::new(k[0], decode_se3(m)?))),
    },
    FactorCodec {
        name: "reprojection_snavely",
        variable_kinds: &["snavely_camera", "point3"],
        measurement_len: 2,
        residual_dim: 2,
        build: |k, m| {
            Ok(Box::new(ReprojectionSnavely::new(
                k[0],
                k[1],
                Vector2::new(m[0], m[1]),
            )))
        },
    },
];

fn encode_as<T: 'static>(v: &dyn Variable, f: impl Fn(&T) -> Vec<f64>) -> Vec<f64> {
    f(v.as_any()
        .downcast_ref::<T>()
        .expect("codec is chosen by the variable's kind"))
}

fn decode_se3(v: &[f64]) -> Result<Se3, String> {
    let q = Quaternion::new(v[6], v[3], v[4], v[5]);
    let norm = q.norm();
    if (norm - 1.0).abs() > 1e-3 {
        return Err(format!(
            "quaternion (qx, qy, qz, qw) has norm {norm}, expected 1"
        ));
    }
    Ok(Se3::new(
        UnitQuaternion::from_quaternion(q),
        Vector3::new(v[0], v[1], v[2]),
    ))
}

pub fn session_kind(name: &str) -> Option<&'static SessionKind> {
    SESSION_KINDS.iter().find(|k| k.name == name)
}

pub fn variable_codec(kind: &str) -> Option<&'static VariableCodec> {
    VARIABLES.iter().find(|c| c.kind == kind)
}

pub fn factor_codec(name: &str) -> Option<&'static FactorCodec> {
    FACTORS.iter().find(|c| c.name == name)
}

/// Encodes a variable for the wire.
pub fn encode_variable(v: &dyn Variable) -> Vec<f64> {
    let codec = variable_codec(v.kind()).expect("every variable kind has a codec");
    (codec.encode)(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_kind_names_known_codecs_and_round_trips() {
        for kind in SESSION_KINDS {
            for v in kind.variable_kinds {
                assert!(variable_codec(v).is_some(), "{} names {v}", kind.name);
            }
            for f in kind.factor_types {
                let codec = factor_codec(f).unwrap_or_else(|| panic!("{} names {f}", kind.name));
                for v in codec.variable_kinds {
                    assert!(kind.variable_kinds.contains(v));
                }
            }
        }
        let se3 = [1.0, 2.0, 3.0, 0.0, 0.6, 0.0, 0.8];
        let codec = variable_codec("se3").unwrap();
        let back = encode_variable((codec.decode)(&se3).unwrap().as_ref());
        for (a, b) in se3.iter().zip(&back) {
            assert!((a - b).abs() < 1e-12);
        }
        assert!((codec.decode)(&[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0]).is_err());
    }
}
