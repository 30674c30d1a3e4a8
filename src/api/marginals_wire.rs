//! The marginals request and answer on the wire (`GET /v1/sessions/{s}/marginals`).

use serde::{Deserialize, Serialize};

use crate::problem::Key;

/// Which variables' marginal covariance to compute.
#[derive(Clone, Debug, Default, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct MarginalsQuery {
    pub keys: Vec<Key>,
    /// Also return the joint covariance of all of them (cross-covariances included).
    #[serde(default)]
    pub joint: bool,
}

/// Marginal covariances at the estimate of `sequence`, in each variable's tangent space.
#[derive(Clone, Debug, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Marginals {
    pub session: String,
    /// The sequence and solve count of the estimate the factorisation was taken at.
    pub sequence: u64,
    pub solves: u64,
    pub variables: Vec<MarginalCovariance>,
    /// Row-major joint covariance, in the order of `variables`, when asked for.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub joint: Option<Vec<Vec<f64>>>,
    /// Variables held fixed (by the client or as gauge anchors): zero covariance, and the
    /// others are conditioned on them.
    pub gauge_fixed: Vec<Key>,
    /// Whether H was factorised for this request or an earlier factorisation at the same
    /// estimate was reused; the factorisation's time, and the whole request's.
    pub reused_factorization: bool,
    pub factorize_seconds: f64,
    pub seconds: f64,
}

#[derive(Clone, Debug, Serialize, Deserialize, utoipa::ToSchema)]
pub struct MarginalCovariance {
    pub key: Key,
    pub kind: String,
    pub fixed: bool,
    /// Over the kind's tangent, in its order and frame (an `se3`'s `[v; ω]` is the body's).
    pub covariance: Vec<Vec<f64>>,
    /// The covariance of its position in the world, 3×3 (z is 0 for planar kinds), whatever
    /// the tangent's frame: what covariance ellipses are drawn from. Absent for kinds without a
    /// position.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub position_covariance: Option<Vec<Vec<f64>>>,
}
