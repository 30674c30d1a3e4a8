//! The factor types a session's client declared when creating it (`factor_types`), compiled
//! once, and how a batch's factor `type` is resolved: a built-in type of the session's kind, else
//! one of these.
//!
//! The declarations are part of the session's creation record, so a restart, a journal replay
//! and a move to another instance of a fleet compile the same types again before any batch is
//! replayed.
//!
//! Types are compiled through the service's [`TypeInterner`]: a definition another session
//! already declared (byte for byte) is shared, not compiled again. Each session is charged its
//! types in full (its `memory_bytes`, `limits.max_factor_type_bytes_per_session`); the server's
//! distinct types count once (`limits.max_factor_type_bytes`).

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::api::catalogue::{self, FactorCodec, SessionKind, SLIDING_WINDOW};
use crate::api::Limits;
use crate::api::ServiceError;
use crate::factors::expression::{ExpressionType, FactorTypeDefinition, InternError, TypeInterner};
use crate::factors::{Factor, INTERNAL_FACTOR_NAMES};
use crate::problem::Key;

/// At most this many declared types per session.
pub const MAX_FACTOR_TYPES: usize = 32;

/// Where a service's sessions compile their types: one [`TypeInterner`] shared by all of them,
/// and the bounds a client's declarations meet (a session's own total, the server's, the time
/// compiling may take). Recovery meets none of them: it rebuilds what was accepted once.
#[derive(Clone, Debug)]
pub struct TypeCompiler {
    pub interner: Arc<TypeInterner>,
    per_session_bytes: usize,
    server_bytes: usize,
    admission: Duration,
}

impl Default for TypeCompiler {
    /// Unbounded, with an interner of its own (a session built outside a service).
    fn default() -> Self {
        Self {
            interner: Arc::default(),
            per_session_bytes: usize::MAX,
            server_bytes: usize::MAX,
            admission: Duration::MAX,
        }
    }
}

impl TypeCompiler {
    pub fn new(limits: &Limits) -> Self {
        Self {
            interner: Arc::default(),
            per_session_bytes: limits.max_factor_type_bytes_per_session,
            server_bytes: limits.max_factor_type_bytes,
            admission: Duration::from_millis(limits.max_admission_ms),
        }
    }
}

/// Whose declarations are compiled: a client's (bounded), or ones accepted before (a recovery,
/// a journal replay) or the operator's (the configuration), which are not.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Declaring {
    Client,
    Trusted,
}

#[derive(Default, Debug, Clone)]
pub struct FactorTypes {
    by_name: HashMap<String, Arc<ExpressionType>>,
    /// Declaration order, for listing.
    names: Vec<String>,
    compiler: TypeCompiler,
    /// What the types hold, each counted in full (shared with other sessions or not): the
    /// session's `memory_bytes` and its bound count this.
    bytes: usize,
}

fn refused(field: String, message: impl Into<String>) -> ServiceError {
    ServiceError::bad_request("invalid_factor_type", field, message)
}

fn refused_in_windows() -> ServiceError {
    refused(
        "factor_types".into(),
        "a sliding_window session is fed fusion messages; declare factor types in graph sessions",
    )
}

impl FactorTypes {
    /// No types yet, compiled through `compiler` when declared.
    pub fn new(compiler: TypeCompiler) -> Self {
        Self {
            compiler,
            ..Self::default()
        }
    }

    /// A recovered session's types, from its creation record (unbounded: accepted once).
    pub fn recovered(
        compiler: TypeCompiler,
        kind: &SessionKind,
        definitions: &[FactorTypeDefinition],
    ) -> Result<Self, ServiceError> {
        let mut types = Self::new(compiler);
        types.extend(kind, definitions, Declaring::Trusted)?;
        Ok(types)
    }

    /// A new session's types: the server-wide ones whose variable kinds a session of `kind`
    /// holds (graph kinds), then the request's `definitions`, which may not reuse their names.
    pub fn for_new_session(
        compiler: TypeCompiler,
        kind: &SessionKind,
        server_wide: &[Arc<ExpressionType>],
        definitions: &[FactorTypeDefinition],
    ) -> Result<Self, ServiceError> {
        let mut types = Self::new(compiler);
        if kind.name != SLIDING_WINDOW {
            for ty in server_wide {
                if ty
                    .variable_kinds()
                    .iter()
                    .all(|k| kind.variable_kinds.contains(k))
                {
                    types.insert(Arc::clone(ty));
                }
            }
        }
        for (i, d) in definitions.iter().enumerate() {
            if types.by_name.contains_key(&d.name) {
                return Err(refused(
                    format!("factor_types[{i}].name"),
                    format!("`{}` is declared in the server's configuration", d.name),
                ));
            }
        }
        types.extend(kind, definitions, Declaring::Client)?;
        Ok(types)
    }

    /// Adds `definitions` (all of them, or none when one is refused); a name already declared
    /// is refused. A client's declarations must also fit the session's and the server's type
    /// memory and be compiled within `limits.max_admission_ms`.
    pub fn extend(
        &mut self,
        kind: &SessionKind,
        definitions: &[FactorTypeDefinition],
        declaring: Declaring,
    ) -> Result<(), ServiceError> {
        if definitions.is_empty() {
            return Ok(());
        }
        let started = Instant::now();
        let mut types = self.clone();
        if kind.name == SLIDING_WINDOW {
            return Err(refused_in_windows());
        }
        if types.names.len() + definitions.len() > MAX_FACTOR_TYPES {
            return Err(refused(
                "factor_types".into(),
                format!(
                    "at most {MAX_FACTOR_TYPES} factor types per session: {} declared, {} more",
                    types.names.len(),
                    definitions.len()
                ),
            ));
        }
        for (i, definition) in definitions.iter().enumerate() {
            let compiled = types.compile_one(i, definition, Some(kind), declaring)?;
            types.insert(compiled);
            if declaring == Declaring::Client {
                types.within_bounds(i, definitions.len(), started)?;
            }
        }
        *self = types;
        Ok(())
    }

    /// After definition `i` of `count`: the session's bound and the admission time.
    fn within_bounds(&self, i: usize, count: usize, started: Instant) -> Result<(), ServiceError> {
        let bound = self.compiler.per_session_bytes;
        if self.bytes > bound {
            return Err(ServiceError::too_large(
                "factor_types_too_large",
                format!(
                    "with definition {i} this session's factor types hold {} bytes, over its bound of {bound} (limits.max_factor_type_bytes_per_session): declare fewer or smaller types",
                    self.bytes
                ),
            )
            .at("factor_types"));
        }
        if started.elapsed() > self.compiler.admission {
            return Err(ServiceError::too_large(
                "factor_types_too_costly",
                format!(
                    "compiling the factor types took longer than limits.max_admission_ms ({} ms): stopped after definition {i} of {count}; declare them in smaller requests",
                    self.compiler.admission.as_millis()
                ),
            )
            .at("factor_types"));
        }
        Ok(())
    }

    /// The server configuration's types, compiled once at start (unbounded: the operator's);
    /// each new graph session then takes those its kinds fit ([`FactorTypes::for_new_session`]).
    pub fn compile_server_wide(
        compiler: TypeCompiler,
        definitions: &[FactorTypeDefinition],
    ) -> Result<Vec<Arc<ExpressionType>>, ServiceError> {
        let mut types = Self::new(compiler);
        for (i, definition) in definitions.iter().enumerate() {
            let compiled = types.compile_one(i, definition, None, Declaring::Trusted)?;
            types.insert(compiled);
        }
        Ok(types
            .names
            .iter()
            .map(|n| Arc::clone(&types.by_name[n]))
            .collect())
    }

    /// Compiles `definitions[i]` for these types (or shares the server's compiled copy): its
    /// name new and not built in, its variables of `kind`'s kinds (any kind for the
    /// server-wide list).
    fn compile_one(
        &self,
        i: usize,
        definition: &FactorTypeDefinition,
        kind: Option<&SessionKind>,
        declaring: Declaring,
    ) -> Result<Arc<ExpressionType>, ServiceError> {
        let field = |suffix: &str| format!("factor_types[{i}].{suffix}");
        if catalogue::factor_codec(&definition.name).is_some()
            || INTERNAL_FACTOR_NAMES.contains(&definition.name.as_str())
        {
            return Err(refused(
                field("name"),
                format!("`{}` is a built-in factor type", definition.name),
            ));
        }
        if self.by_name.contains_key(&definition.name) {
            return Err(refused(
                field("name"),
                format!("`{}` is declared twice", definition.name),
            ));
        }
        for (k, v) in definition.variables.iter().enumerate() {
            if let Some(kind) = kind.filter(|kind| !kind.variable_kinds.contains(&v.kind.as_str()))
            {
                return Err(refused(
                    field(&format!("variables[{k}].kind")),
                    format!(
                        "a {} session holds variables of kind {:?}, not `{}`",
                        kind.name, kind.variable_kinds, v.kind
                    ),
                ));
            }
        }
        let bound = (declaring == Declaring::Client).then_some(self.compiler.server_bytes);
        match self.compiler.interner.compile(definition.clone(), bound) {
            Ok(compiled) => Ok(compiled),
            Err(InternError::Definition(e)) => Err(refused(field(&e.path), e.message)),
            Err(full @ InternError::ServerFull { .. }) => Err(ServiceError::too_large(
                "factor_types_server_full",
                format!("definition {i}: {full}; types other sessions already declared are shared at no cost"),
            )
            .at("factor_types")),
        }
    }

    /// Bytes these types hold, each counted in full.
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    fn insert(&mut self, compiled: Arc<ExpressionType>) {
        self.bytes += compiled.memory_bytes();
        self.names.push(compiled.name().to_string());
        self.by_name.insert(compiled.name().to_string(), compiled);
    }

    /// Those of `definitions` not declared yet (a snapshot lists every type, the creation
    /// record the first ones).
    pub fn missing(&self, definitions: Vec<FactorTypeDefinition>) -> Vec<FactorTypeDefinition> {
        definitions
            .into_iter()
            .filter(|d| !self.by_name.contains_key(&d.name))
            .collect()
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

impl super::Session {
    /// The factor types declared so far (a read lock, held by batches while they validate).
    pub fn factor_types(&self) -> std::sync::RwLockReadGuard<'_, FactorTypes> {
        self.factor_types.read().unwrap_or_else(|p| p.into_inner())
    }

    /// Gives a new session the types of its creation request.
    pub(crate) fn set_factor_types(&self, types: FactorTypes) {
        *self.factor_types.write().unwrap_or_else(|p| p.into_inner()) = types;
    }

    /// Declares more factor types in a running graph session: compiled whole (all or none),
    /// journalled before they are answered, in order with the batches (the session's lock is
    /// held), and usable by every batch after.
    pub fn define_factor_types(
        &self,
        definitions: Vec<FactorTypeDefinition>,
    ) -> Result<crate::api::wire::SessionInfo, ServiceError> {
        if !matches!(self.engine, super::Engine::Graph(_)) {
            return Err(refused_in_windows());
        }
        {
            let st = self.lock();
            if st.schedule.phase.is_deleted() {
                return Err(self.gone());
            }
            let mut extended = self.factor_types().clone();
            extended.extend(self.kind, &definitions, Declaring::Client)?;
            let mut durable = self.durable.lock().unwrap_or_else(|p| p.into_inner());
            if let Some(d) = durable.as_mut() {
                d.append(
                    &self.name,
                    &crate::journal::Entry::FactorTypes {
                        factor_types: definitions,
                    },
                )?;
            }
            *self.factor_types.write().unwrap_or_else(|p| p.into_inner()) = extended;
        }
        Ok(self.info())
    }

    /// Replays declared types (a journal entry, a snapshot's list): those already known are
    /// skipped.
    pub(super) fn restore_factor_types(
        &self,
        definitions: Vec<FactorTypeDefinition>,
    ) -> Result<(), String> {
        let mut types = self.factor_types.write().unwrap_or_else(|p| p.into_inner());
        let missing = types.missing(definitions);
        types
            .extend(self.kind, &missing, Declaring::Trusted)
            .map_err(|e| e.body.message)
    }
}
