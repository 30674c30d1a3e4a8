//! Possibly wrong loop closures, as the wire shows them: the mark on a factor, the session's
//! policy, what `GET /v1/sessions/{s}/outliers` answers and the `outliers` event.
//!
//! A factor marked `"outlier": "auto"` (or any loop closure of a session created with
//! `"outliers": "auto"`) is a *candidate*: accepted, acknowledged and journalled like any
//! factor, but it enters the estimate only once the service decided it is consistent with the
//! map (see `session::outliers`). The decisions are visible here and change as evidence comes.

use serde::{Deserialize, Serialize};

use super::wire::FactorId;
use crate::problem::Key;

/// A factor's `outlier` field.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum OutlierMark {
    /// It may be wrong (place recognition, scan matching): the service decides whether it
    /// enters the estimate, and may change its mind as the map grows.
    Auto,
    /// It is right: never held out, whatever the session's policy.
    Trusted,
}

/// `outliers` at session creation: which factors are candidates without a mark of their own.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum OutlierPolicy {
    /// Only factors marked `"outlier": "auto"`.
    #[default]
    Off,
    /// Also every loop closure: a `between_se2`/`between_se3` whose two keys are not
    /// consecutive (odometry joins consecutive keys; GTSAM `Symbol` keys of one robot are).
    Auto,
}

impl OutlierPolicy {
    pub fn is_off(&self) -> bool {
        *self == OutlierPolicy::Off
    }
}

/// Whether a factor of type `factor_type` on `keys` is a candidate under `policy` with `mark`.
pub fn is_candidate(
    policy: OutlierPolicy,
    mark: Option<OutlierMark>,
    factor_type: &str,
    keys: &[Key],
) -> bool {
    match mark {
        Some(OutlierMark::Auto) => true,
        Some(OutlierMark::Trusted) => false,
        None => {
            policy == OutlierPolicy::Auto
                && matches!(factor_type, "between_se2" | "between_se3")
                && matches!(keys, [a, b] if a.abs_diff(*b) != 1)
        }
    }
}

/// One candidate and where it stands.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct CandidateReport {
    pub factor_id: FactorId,
    pub keys: Vec<Key>,
    /// The innovation's squared Mahalanobis distance when the gate last weighed it (the rise
    /// of the least-squares cost it would cause, χ²-distributed with the residual's dimension
    /// for a correct measurement); absent when graduated non-convexity decided.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub distance: Option<f64>,
    /// `gate` (weighed alone against the streamed estimate) or `graduated_non_convexity` (all
    /// candidates together, in a batch solve).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub decided_by: Option<String>,
}

/// `GET /v1/sessions/{s}/outliers`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct OutliersReport {
    pub session: String,
    pub policy: OutlierPolicy,
    /// Candidates in the estimate.
    pub accepted: u64,
    /// Candidates not decided yet (a variable of theirs has not been solved).
    pub pending: Vec<CandidateReport>,
    /// Candidates held out of the estimate as inconsistent with it.
    pub rejected: Vec<CandidateReport>,
    /// Batch solves that decided every candidate again together.
    pub consolidations: u64,
    /// The χ² confidence of the gate: a candidate passes while its distance stays within the
    /// quantile of its residual's dimension at this confidence.
    pub gate_confidence: f64,
}

/// The `outliers` event: decisions a solve took.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct OutlierDecisions {
    /// The session sequence the solve reflected.
    pub sequence: u64,
    /// `gate` or `graduated_non_convexity`.
    pub decided_by: String,
    /// Candidates that entered the estimate (or stay in it).
    pub accepted: Vec<CandidateReport>,
    /// Candidates held out (or taken out).
    pub rejected: Vec<CandidateReport>,
}
