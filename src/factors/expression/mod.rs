//! User-defined factors: a residual written as an expression over the factor's variables and
//! parameters, compiled once into a tape and differentiated in forward mode.
//!
//! A client declares a factor type when it creates a session (`factor_types`): its name, the
//! kinds of the variables it connects, its parameters (the measurement, in order) and the
//! residual as a JSON expression tree (see [`lower`] for the language, [`OPERATIONS`] for every
//! operation). [`ExpressionType::compile`] type-checks and lowers it, bounds its size and cost,
//! and checks the forward-mode Jacobian against central differences through each variable's
//! retraction (the same helper as every built-in factor) at random values; after that the type
//! builds [`ExpressionFactor`]s like any built-in factor's `WIRE.build`.
//!
//! Differentiation: the derivative of the residual with respect to the tangent perturbation δ
//! of each variable at δ = 0, i.e. the Jacobian the solver expects. The variables enter the tape
//! already retracted — `se2` as `(x + δx, y + δy, θ + δθ)`, `se3` as `(R Exp(ω), t + R v)`,
//! `snavely_camera` as `(Exp(ω) R, t + δt, k + δk)`, points additively — so the seeds are the
//! retractions' first-order terms.

mod builder;
mod check;
mod factor;
mod interner;
mod lower;
mod memory;
mod tape;
#[cfg(test)]
mod tests;

use serde::{Deserialize, Serialize};

pub use factor::{ExpressionFactor, ExpressionType};
pub use interner::{InternError, TypeInterner, TypesHeld};
pub use lower::{MAX_DEPTH, MAX_NODES, OPERATIONS};

/// A factor type as a client declares it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct FactorTypeDefinition {
    /// The factor's wire `type`: 1-64 characters of `[a-z0-9_]`, starting with a letter, not a
    /// built-in type.
    pub name: String,
    /// The variables it connects, in key order.
    pub variables: Vec<Declared>,
    /// The measurement's parts, in order; the wire measurement is their encodings concatenated
    /// (`se3`: 7 numbers, `se2`: 3, `vector` of `len`: len, `scalar`: 1).
    #[serde(default)]
    pub parameters: Vec<Declared>,
    /// The residual: an expression of type scalar or vector (see docs/guide/factor-types.md).
    #[schema(value_type = Object)]
    pub residual: serde_json::Value,
    /// When given, must equal the residual's length.
    #[serde(default)]
    pub residual_dim: Option<usize>,
    #[serde(default)]
    pub description: Option<String>,
}

/// A named variable or parameter of a definition.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Declared {
    pub name: String,
    /// Variables: `se2`, `se3`, `point2`, `point3`, `snavely_camera`. Parameters: those except
    /// `snavely_camera`, plus `scalar` and `vector` (with `len`).
    pub kind: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub len: Option<usize>,
}

/// Why a definition was refused: the offending node or field, relative to the definition
/// (`residual.compose[1]`, `variables[0].kind`), and what is wrong there.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{path}: {message}")]
pub struct DefinitionError {
    pub path: String,
    pub message: String,
}

/// Bounds on a definition besides the expression's size.
pub const MAX_VARIABLES: usize = 8;
pub const MAX_PARAMETERS: usize = 32;
pub const MAX_MEASUREMENT: usize = 256;
pub const MAX_RESIDUAL: usize = 64;
/// Tape slots × (1 + tangent lanes): bounds one evaluation with its Jacobian (≈ flops).
pub const MAX_COST: usize = 400_000;
