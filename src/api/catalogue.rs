//! What a session may contain, by name: variable kinds with their wire encoding, factor types with
//! their decoders, and session kinds as sets of both.
//!
//! The session layer only ever goes through this table, so a new kind of problem (bundle
//! adjustment, sliding-window fusion) is a new entry here plus its variables and factors — the
//! session, the worker pool and the transports do not change.
//!
//! Each variable kind declares its wire form once ([`VariableWire`], next to its `Variable` impl
//! in `variables/`), each factor type once ([`FactorWire`], the `WIRE` const in its file in
//! `factors/`); this file only lists them. `api::factor_schema` turns the same list into
//! `proto/v1/factors.schema.json`. A new factor is its file plus one line here.

use crate::factors::{
    BearingRangeSe2, BearingSe2, BetweenSe2, BetweenSe3, GnssLeverArmSe3, GnssPositionSe3,
    PositionSe3Point3, PriorSe2, PriorSe3, RangeSe2, RangeSe2Point2, RangeSe3, RangeSe3Point3,
    ReprojectionSnavely,
};
use crate::problem::{Gauge, Variable};
use crate::solver::SolverOptions;
use crate::variables::{point2, point3, se2, se3, snavely_camera};

pub use crate::factors::{BuildFactor, FactorWire};
pub use crate::variables::{DecodeVariable, Shape, VariableWire};

/// How one variable kind travels on the wire (its declaration in `variables/`).
pub type VariableCodec = VariableWire;
/// How one factor type is built from its wire form (its declaration in `factors/`).
pub type FactorCodec = FactorWire;

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
        description: "SE(2) poses and point2 landmarks with relative-pose, prior, bearing-range, bearing-only and range factors",
        variable_kinds: &["se2", "point2"],
        factor_types: &[
            "between_se2",
            "prior_se2",
            "bearing_range_se2",
            "bearing_se2",
            "range_se2_point2",
            "range_se2",
        ],
        gauge: Gauge::AnchorComponents,
        eliminate: &[],
        default_options: SolverOptions::default,
    },
    SessionKind {
        name: "pose_graph_3d",
        description: "SE(3) poses and point3 landmarks with relative-pose, prior, GNSS position (with or without a lever arm), landmark position and range factors",
        variable_kinds: &["se3", "point3"],
        factor_types: &[
            "between_se3",
            "prior_se3",
            "gnss_position_se3",
            "gnss_lever_arm_se3",
            "position_se3_point3",
            "range_se3_point3",
            "range_se3",
        ],
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

const VARIABLES: &[&VariableWire] = &[
    &se2::WIRE,
    &se3::WIRE,
    &snavely_camera::WIRE,
    &point3::WIRE,
    &point2::WIRE,
];

const FACTORS: &[&FactorWire] = &[
    &BetweenSe2::WIRE,
    &PriorSe2::WIRE,
    &BetweenSe3::WIRE,
    &PriorSe3::WIRE,
    &ReprojectionSnavely::WIRE,
    &GnssPositionSe3::WIRE,
    &BearingRangeSe2::WIRE,
    &BearingSe2::WIRE,
    &RangeSe2Point2::WIRE,
    &RangeSe2::WIRE,
    &GnssLeverArmSe3::WIRE,
    &PositionSe3Point3::WIRE,
    &RangeSe3Point3::WIRE,
    &RangeSe3::WIRE,
];

/// Every factor type a batch may name, in catalogue order.
pub fn factors() -> &'static [&'static FactorWire] {
    FACTORS
}

/// Every variable kind a batch may name, in catalogue order.
pub fn variables() -> &'static [&'static VariableWire] {
    VARIABLES
}

pub fn session_kind(name: &str) -> Option<&'static SessionKind> {
    SESSION_KINDS.iter().find(|k| k.name == name)
}

pub fn variable_codec(kind: &str) -> Option<&'static VariableCodec> {
    VARIABLES.iter().copied().find(|c| c.kind == kind)
}

pub fn factor_codec(name: &str) -> Option<&'static FactorCodec> {
    FACTORS.iter().copied().find(|c| c.name == name)
}

/// Encodes a variable for the wire.
pub fn encode_variable(v: &dyn Variable) -> Vec<f64> {
    let mut out = Vec::new();
    encode_variable_into(v, &mut out);
    out
}

/// Encodes a variable for the wire into `out` (its contents replaced, its allocation reused).
pub fn encode_variable_into(v: &dyn Variable, out: &mut Vec<f64>) {
    let codec = variable_codec(v.kind()).expect("every variable kind has a codec");
    (codec.encode)(v, out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashSet;

    #[test]
    fn names_are_unique() {
        let mut seen = HashSet::new();
        for name in FACTORS.iter().map(|f| f.name) {
            assert!(seen.insert(name), "factor type {name} declared twice");
        }
        let mut seen = HashSet::new();
        for kind in VARIABLES.iter().map(|v| v.kind) {
            assert!(seen.insert(kind), "variable kind {kind} declared twice");
        }
        let mut seen = HashSet::new();
        for name in SESSION_KINDS.iter().map(|k| k.name) {
            assert!(seen.insert(name), "session kind {name} declared twice");
        }
    }

    #[test]
    fn every_factor_names_known_variable_kinds_and_documents_its_parts() {
        for f in FACTORS {
            assert!(!f.variable_kinds.is_empty(), "{} connects nothing", f.name);
            for v in f.variable_kinds {
                assert!(
                    variable_codec(v).is_some(),
                    "{} names unknown kind {v}",
                    f.name
                );
            }
            assert_eq!(f.key_names.len(), f.variable_kinds.len(), "{}", f.name);
            assert_eq!(f.measurement.len(), f.measurement_len, "{}", f.name);
            assert!(
                f.residual_dim > 0 && !f.description.is_empty(),
                "{}",
                f.name
            );
        }
        for v in VARIABLES {
            assert_eq!(v.components.len(), v.len, "{}", v.kind);
        }
    }

    /// A factor built from its declaration answers with the declaration's name, kinds and
    /// residual dimension (the factor's trait methods read them from `WIRE`).
    #[test]
    fn built_factors_agree_with_their_declaration() {
        for f in FACTORS {
            let keys: Vec<_> = (0..f.variable_kinds.len() as u64).collect();
            // A measurement every declared encoding accepts: an se3's identity quaternion.
            let mut m = vec![0.0; f.measurement_len];
            if f.measurement_len == 7 {
                m[6] = 1.0;
            }
            let built = (f.build)(&keys, &m).unwrap_or_else(|e| panic!("{}: {e}", f.name));
            assert_eq!(built.name(), f.name);
            assert_eq!(built.variable_kinds(), f.variable_kinds);
            assert_eq!(built.residual_dim(), f.residual_dim);
            assert_eq!(built.keys(), keys.as_slice());
        }
    }

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
