//! Factors: residual functions of a few variables, with analytic Jacobians.
//!
//! A factor only computes its *unwhitened* error `e(x)` and `∂e/∂δ` for each variable it touches
//! (δ in that variable's tangent space, as defined by its retraction). Weighting by the square-root
//! information and robust kernels is applied uniformly by `problem::FactorEntry`, so every factor file
//! contains only its own mathematics.

/// Inside `impl Factor for T`: the methods a factor with a `WIRE: FactorWire` declaration and a
/// `keys` field answers from them (name, keys, residual dimension, variable kinds) and `as_any`,
/// so each is stated once and a factor file writes only its residual and Jacobians.
macro_rules! answered_by_wire {
    () => {
        fn name(&self) -> &str {
            Self::WIRE.name
        }
        fn keys(&self) -> &[$crate::variables::Key] {
            &self.keys
        }
        fn residual_dim(&self) -> usize {
            Self::WIRE.residual_dim
        }
        fn variable_kinds(&self) -> &[&'static str] {
            Self::WIRE.variable_kinds
        }
        fn as_any(&self) -> &dyn ::std::any::Any {
            self
        }
    };
}

/// A range factor's declaration (`range_se2`, `range_se3_point3`, …): the struct, two keys and
/// the measured range in metres, with `new` and its `WIRE` (one number, refused when negative).
/// Each range factor's file adds its residual and Jacobians.
macro_rules! range_factor {
    ($(#[$doc:meta])* $name:ident, $wire:literal, $kinds:expr, $key_names:expr, $description:literal) => {
        $(#[$doc])*
        #[derive(Clone, Debug)]
        pub struct $name {
            keys: [$crate::variables::Key; 2],
            /// Measured range, metres.
            pub range: f64,
        }

        impl $name {
            #[doc = concat!("The wire form: `", $wire, "`.")]
            pub const WIRE: $crate::factors::FactorWire = $crate::factors::FactorWire {
                name: $wire,
                variable_kinds: $kinds,
                key_names: $key_names,
                measurement_len: 1,
                measurement: &["range"],
                residual_dim: 1,
                description: $description,
                build: |k, m| {
                    if m[0] < 0.0 {
                        return Err(format!("a range cannot be negative, got {}", m[0]));
                    }
                    Ok(Box::new($name::new(k[0], k[1], m[0])))
                },
            };

            pub fn new(a: $crate::variables::Key, b: $crate::variables::Key, range: f64) -> Self {
                Self { keys: [a, b], range }
            }
        }
    };
}

pub mod autodiff;
pub mod bearing_range_se2;
pub mod bearing_se2;
pub mod between_se2;
pub mod between_se3;
pub mod expression;
pub mod gnss_lever_arm_se3;
pub mod gnss_position_se3;
pub mod imu_preintegration;
pub mod marginal_prior;
pub mod noise;
pub mod photometric_patch;
pub mod position_se3_point3;
pub mod prior_nav;
pub mod prior_se2;
pub mod prior_se3;
pub mod range_se2;
pub mod range_se2_point2;
pub mod range_se3;
pub mod range_se3_point3;
pub mod relative_pose_nav;
pub mod reprojection_snavely;
pub mod robust;
pub mod testing;

use std::any::Any;
use std::fmt::Debug;

pub use bearing_range_se2::BearingRangeSe2;
pub use bearing_se2::BearingSe2;
pub use between_se2::BetweenSe2;
pub use between_se3::BetweenSe3;
pub use gnss_lever_arm_se3::GnssLeverArmSe3;
pub use gnss_position_se3::GnssPositionSe3;
pub use imu_preintegration::ImuFactor;
pub use marginal_prior::MarginalPrior;
pub use noise::SqrtInformation;
pub use photometric_patch::PhotometricPatch;
pub use position_se3_point3::PositionSe3Point3;
pub use prior_nav::{PosePriorNav, PositionPriorNav};
pub use prior_se2::PriorSe2;
pub use prior_se3::PriorSe3;
pub use range_se2::RangeSe2;
pub use range_se2_point2::RangeSe2Point2;
pub use range_se3::RangeSe3;
pub use range_se3_point3::RangeSe3Point3;
pub use relative_pose_nav::RelativePoseNav;
pub use reprojection_snavely::ReprojectionSnavely;
pub use robust::RobustKernel;

use crate::variables::{Key, Variable};

/// The names of the factors the server builds itself (the window's IMU, navigation-state and
/// marginal factors, the direct-BA patches), and `prior_nav`, their family's name: not in the
/// wire catalogue, yet reserved, so that a user-defined type can never be taken for one.
pub const INTERNAL_FACTOR_NAMES: &[&str] = &[
    imu_preintegration::NAME,
    relative_pose_nav::NAME,
    prior_nav::POSE_NAME,
    prior_nav::POSITION_NAME,
    "prior_nav",
    marginal_prior::NAME,
    photometric_patch::NAME,
];

/// Builds a factor from its keys and measurement (lengths already checked), or says why not.
pub type BuildFactor = fn(&[Key], &[f64]) -> Result<Box<dyn Factor>, String>;

/// How one factor type travels on the wire: declared once, as `WIRE` next to the factor's
/// mathematics, listed by `api::catalogue` and turned into `proto/v1/factors.schema.json` by
/// `api::factor_schema`. The factor's own `name`, `residual_dim` and `variable_kinds` return
/// these fields, so the code and the wire cannot disagree.
pub struct FactorWire {
    /// The wire `type` (`"between_se2"`).
    pub name: &'static str,
    /// Kinds of the variables it connects, in key order.
    pub variable_kinds: &'static [&'static str],
    /// What each key is, in key order, for documentation (`["i", "j"]`).
    pub key_names: &'static [&'static str],
    /// Number of values in the wire measurement.
    pub measurement_len: usize,
    /// The measurement's components in order, for documentation (`["x", "y", "theta"]`).
    pub measurement: &'static [&'static str],
    /// Dimension of the residual: the information matrix is its square, `sigmas` its length.
    pub residual_dim: usize,
    /// One paragraph for the schema: what is measured and the residual's order and units.
    pub description: &'static str,
    pub build: BuildFactor,
}

/// Why a factor could not be evaluated at the given variables.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum EvaluationError {
    #[error("factor expects a variable of kind {expected} at position {position}, found {found}")]
    WrongKind {
        position: usize,
        expected: &'static str,
        found: &'static str,
    },
    /// The factor's own code failed: a residual written outside the library (a Python
    /// callback in the in-process API) raised or answered something of the wrong shape.
    #[error("{factor}: {message}")]
    Failed { factor: String, message: String },
}

pub trait Factor: Debug + Send + Sync {
    /// Short name for errors and summaries (`"between_se2"`; a user-defined type's own name).
    fn name(&self) -> &str;
    fn keys(&self) -> &[Key];
    fn residual_dim(&self) -> usize;
    /// The kind expected at each key, checked when the factor is added to a problem.
    fn variable_kinds(&self) -> &[&'static str];
    /// Writes `e(x)` into `error` and, when asked, `∂e/∂δ_k` for every variable `k` into
    /// `jacobian`, laid out row-major as `[J_0 | J_1 | …]` (residual_dim × Σ tangent dims).
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError>;
    fn as_any(&self) -> &dyn Any;
    /// The value of the variable at position `target` that makes this factor's error zero given
    /// the others (`known[k]` is `None` only at `target`), when the measurement determines it: a
    /// between factor's far end, a prior's pose. Used to predict initial guesses for new
    /// variables a client sends without one.
    fn predict(
        &self,
        _known: &[Option<&dyn Variable>],
        _target: usize,
    ) -> Option<Box<dyn Variable>> {
        None
    }
}

/// Downcasts variable `position` to `T`, or says which kind was expected.
/// Whether `factor` can be evaluated at `values` (in its key order) with a finite residual: a
/// factor that cannot (a point at a camera's centre, poses at 1e308) gives the solver nothing.
pub fn residual_is_finite(factor: &dyn Factor, values: &[&dyn Variable]) -> bool {
    let mut e = vec![0.0; factor.residual_dim()];
    factor.evaluate(values, &mut e, None).is_ok() && e.iter().all(|v| v.is_finite())
}

/// Whether the factor's cost `|R e|²` is finite at `values`: a finite residual can still
/// overflow once weighted and squared (a prior 1e155 away), and one infinite cost makes the
/// whole problem's χ² infinite, so no step could ever be accepted.
pub fn cost_is_finite(
    factor: &dyn Factor,
    sqrt_information: &SqrtInformation,
    values: &[&dyn Variable],
) -> bool {
    let mut e = vec![0.0; factor.residual_dim()];
    if factor.evaluate(values, &mut e, None).is_err() {
        return false;
    }
    let mut whitened = vec![0.0; e.len()];
    sqrt_information.whiten_vector(&e, &mut whitened);
    whitened.iter().map(|v| v * v).sum::<f64>().is_finite()
}

pub(crate) fn expect_kind<'a, T: Variable>(
    variables: &[&'a dyn Variable],
    position: usize,
    expected: &'static str,
) -> Result<&'a T, EvaluationError> {
    let v = variables[position];
    v.as_any()
        .downcast_ref::<T>()
        .ok_or(EvaluationError::WrongKind {
            position,
            expected,
            found: v.kind(),
        })
}
