//! The factor types a session's client declared when creating it (`factor_types`), compiled
//! once, and how a batch's factor `type` is resolved: a built-in type of the session's kind, else
//! one of these.
//!
//! The declarations are part of the session's creation record, so a restart, a journal replay
//! and a move to another instance of a fleet compile the same types again before any batch is
//! replayed.

use std::collections::HashMap;
use std::sync::Arc;

use crate::api::catalogue::{self, FactorCodec, SessionKind, SLIDING_WINDOW};
use crate::api::ServiceError;
use crate::factors::expression::{ExpressionType, FactorTypeDefinition};
use crate::factors::Factor;
use crate::problem::Key;

/// At most this many declared types per session.
pub const MAX_FACTOR_TYPES: usize = 32;

#[derive(Default, Debug)]
pub struct FactorTypes {
    by_name: HashMap<String, Arc<ExpressionType>>,
    /// Declaration order, for listing.
    names: Vec<String>,
}

fn refused(field: String, message: impl Into<String>) -> ServiceError {
    ServiceError::bad_request("invalid_factor_type", field, message)
}

impl FactorTypes {
    /// Compiles a creation request's declarations for a session of `kind`; errors name the
    /// field or expression node (`factor_types[0].residual.compose[1]`).
    pub fn compile(
        kind: &SessionKind,
        definitions: &[FactorTypeDefinition],
    ) -> Result<Self, ServiceError> {
        let mut types = Self::default();
        if definitions.is_empty() {
            return Ok(types);
        }
        if kind.name == SLIDING_WINDOW {
            return Err(refused(
                "factor_types".into(),
                "a sliding_window session is fed fusion messages; declare factor types in graph sessions",
            ));
        }
        if definitions.len() > MAX_FACTOR_TYPES {
            return Err(refused(
                "factor_types".into(),
                format!(
                    "at most {MAX_FACTOR_TYPES} factor types per session, got {}",
                    definitions.len()
                ),
            ));
        }
        for (i, definition) in definitions.iter().enumerate() {
            let field = |suffix: &str| format!("factor_types[{i}].{suffix}");
            if catalogue::factor_codec(&definition.name).is_some() {
                return Err(refused(
                    field("name"),
                    format!("`{}` is a built-in factor type", definition.name),
                ));
            }
            if types.by_name.contains_key(&definition.name) {
                return Err(refused(
                    field("name"),
                    format!("`{}` is declared twice", definition.name),
                ));
            }
            for (k, v) in definition.variables.iter().enumerate() {
                if !kind.variable_kinds.contains(&v.kind.as_str()) {
                    return Err(refused(
                        field(&format!("variables[{k}].kind")),
                        format!(
                            "a {} session holds variables of kind {:?}, not `{}`",
                            kind.name, kind.variable_kinds, v.kind
                        ),
                    ));
                }
            }
            let compiled = ExpressionType::compile(definition.clone())
                .map_err(|e| refused(field(&e.path), e.message))?;
            types.names.push(definition.name.clone());
            types.by_name.insert(definition.name.clone(), compiled);
        }
        Ok(types)
    }

    pub fn names(&self) -> &[String] {
        &self.names
    }

    /// The declarations, in order (for the session's creation record).
    pub fn definitions(&self) -> Vec<FactorTypeDefinition> {
        self.names
            .iter()
            .map(|n| self.by_name[n].definition.clone())
            .collect()
    }

    /// The codec of factor type `name` in a session of `kind`.
    pub(crate) fn resolve(&self, kind: &SessionKind, name: &str) -> Option<Codec<'_>> {
        if kind.factor_types.contains(&name) {
            return catalogue::factor_codec(name).map(Codec::BuiltIn);
        }
        self.by_name.get(name).map(Codec::Declared)
    }
}

/// A factor type as a batch uses it: built in, or declared by the session's client.
pub(crate) enum Codec<'a> {
    BuiltIn(&'static FactorCodec),
    Declared(&'a Arc<ExpressionType>),
}

impl Codec<'_> {
    pub fn name(&self) -> &str {
        match self {
            Codec::BuiltIn(c) => c.name,
            Codec::Declared(t) => t.name(),
        }
    }
    pub fn variable_kinds(&self) -> &[&'static str] {
        match self {
            Codec::BuiltIn(c) => c.variable_kinds,
            Codec::Declared(t) => t.variable_kinds(),
        }
    }
    pub fn measurement_len(&self) -> usize {
        match self {
            Codec::BuiltIn(c) => c.measurement_len,
            Codec::Declared(t) => t.measurement_len(),
        }
    }
    pub fn residual_dim(&self) -> usize {
        match self {
            Codec::BuiltIn(c) => c.residual_dim,
            Codec::Declared(t) => t.residual_dim(),
        }
    }
    pub fn build(&self, keys: &[Key], measurement: &[f64]) -> Result<Box<dyn Factor>, String> {
        match self {
            Codec::BuiltIn(c) => (c.build)(keys, measurement),
            Codec::Declared(t) => Ok(Box::new(t.build(keys, measurement)?)),
        }
    }
}
