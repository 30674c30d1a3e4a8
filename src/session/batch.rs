//! Validating a batch against a session before anything of it is applied.
//!
//! [`prepare`] checks every element against the session's catalogue and its current keys (the
//! estimate mirror, which already includes batches waiting for a running solve), predicts missing
//! initial guesses, and returns typed, ready-to-apply parts. Applying them to the problem cannot
//! fail afterwards, so a batch is applied whole or, when `prepare` errs, not at all.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::time::{Duration, Instant};

use nalgebra::DMatrix;

use super::factor_types::FactorTypes;
pub(crate) use super::prepared::{NewVariable, PreparedBatch, PreparedFactor};
use super::MirrorEntry;
use crate::api::catalogue::{self, SessionKind};
use crate::api::outliers::{is_candidate, OutlierPolicy};
use crate::api::wire::{Batch, FactorId, FactorSpec};
use crate::api::ServiceError;
use crate::factors::{robust, SqrtInformation};
use crate::problem::{Key, Variable};
use crate::solver::budget::FACTORS_PER_CHECK;

/// What `prepare` needs to know about the session.
pub(crate) struct SessionView<'a> {
    pub kind: &'static SessionKind,
    pub mirror: &'a BTreeMap<Key, MirrorEntry>,
    pub live_factors: &'a HashSet<FactorId>,
    /// Factor types the session's client declared.
    pub factor_types: &'a FactorTypes,
    /// Which factors are possibly wrong loop closures without a mark of their own.
    pub outliers: OutlierPolicy,
    /// When admitting the batch must be over; `None` for a journal replay, which restores what
    /// was accepted once.
    pub deadline: Option<AdmissionDeadline>,
}

/// Admission runs under the session's lock, and a user-defined factor can cost milliseconds to
/// build and check, so it has a bound of its own, `limits.max_admission_ms`, checked every
/// [`FACTORS_PER_CHECK`] factors (unbounded, a large batch held the session past any solve's).
#[derive(Debug, Clone, Copy)]
pub(crate) struct AdmissionDeadline {
    pub at: Instant,
    pub limit_ms: u64,
}

impl AdmissionDeadline {
    pub fn after(limit_ms: u64) -> Self {
        Self {
            at: Instant::now() + Duration::from_millis(limit_ms),
            limit_ms,
        }
    }
}

/// Checks the deadline every [`FACTORS_PER_CHECK`] factors: 413 `batch_too_costly` once it is
/// past (the batch is refused whole; smaller batches of the same factors are admitted).
fn in_time(view: &SessionView, done: usize, total: usize, step: &str) -> Result<(), ServiceError> {
    let Some(deadline) = view
        .deadline
        .filter(|_| done.is_multiple_of(FACTORS_PER_CHECK))
    else {
        return Ok(());
    };
    if Instant::now() < deadline.at {
        return Ok(());
    }
    Err(ServiceError::too_large(
        "batch_too_costly",
        format!(
            "admitting the batch took longer than limits.max_admission_ms ({} ms): {step} stopped at factor {done} of {total}; send its factors in smaller batches",
            deadline.limit_ms
        ),
    )
    .at("factors"))
}

/// The name of a field in a request, formatted only when an error names it (formatting the
/// names of a valid batch's thousand factors cost about 5% of ingest, measured).
type FieldName<'a> = &'a dyn Fn() -> String;

fn finite(values: &[f64], field: FieldName) -> Result<(), ServiceError> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(k) => {
            let field = field();
            Err(ServiceError::bad_request(
                "non_finite",
                format!("{field}[{k}]"),
                format!("{field}[{k}] is not a finite number"),
            ))
        }
        None => Ok(()),
    }
}

fn decode_value(
    kind: &str,
    value: &[f64],
    field: FieldName,
) -> Result<Box<dyn Variable>, ServiceError> {
    let codec = catalogue::variable_codec(kind).expect("kind checked against the catalogue");
    if value.len() != codec.len {
        return Err(ServiceError::bad_request(
            "wrong_dimension",
            field(),
            format!(
                "a {kind} value has {} numbers, got {}",
                codec.len,
                value.len()
            ),
        ));
    }
    finite(value, field)?;
    (codec.decode)(value).map_err(|m| ServiceError::bad_request("invalid_value", field(), m))
}

/// The factor's square-root information; `factor` names the factor (`factors[3]`) in errors.
fn information(
    spec: &FactorSpec,
    dim: usize,
    factor: FieldName,
) -> Result<SqrtInformation, ServiceError> {
    let information_field = || format!("{}.information", factor());
    let matrix = match (&spec.information, &spec.sigmas) {
        (Some(_), Some(_)) | (None, None) => {
            return Err(ServiceError::bad_request(
                "missing_noise",
                factor(),
                "give exactly one of `information` and `sigmas`",
            ))
        }
        (Some(info), None) => {
            finite(info, &information_field)?;
            if info.len() == dim * dim {
                DMatrix::from_row_slice(dim, dim, info)
            } else if info.len() == dim * (dim + 1) / 2 {
                let mut m = DMatrix::zeros(dim, dim);
                let mut k = 0;
                for i in 0..dim {
                    for j in i..dim {
                        m[(i, j)] = info[k];
                        m[(j, i)] = info[k];
                        k += 1;
                    }
                }
                m
            } else {
                return Err(ServiceError::bad_request(
                    "wrong_dimension",
                    information_field(),
                    format!(
                        "information needs {} (full) or {} (upper triangle) numbers, got {}",
                        dim * dim,
                        dim * (dim + 1) / 2,
                        info.len()
                    ),
                ));
            }
        }
        (None, Some(sigmas)) => {
            let sigmas_field = || format!("{}.sigmas", factor());
            finite(sigmas, &sigmas_field)?;
            if sigmas.len() != dim {
                return Err(ServiceError::bad_request(
                    "wrong_dimension",
                    sigmas_field(),
                    format!("sigmas needs {dim} numbers, got {}", sigmas.len()),
                ));
            }
            if let Some(k) = sigmas.iter().position(|s| *s <= 0.0) {
                return Err(ServiceError::bad_request(
                    "bad_information",
                    format!("{}[{k}]", sigmas_field()),
                    "sigmas must be positive",
                ));
            }
            DMatrix::from_diagonal(&nalgebra::DVector::from_iterator(
                dim,
                sigmas.iter().map(|s| 1.0 / (s * s)),
            ))
        }
    };
    SqrtInformation::from_information(&matrix).map_err(|e| {
        ServiceError::bad_request("bad_information", information_field(), e.to_string())
    })
}

/// The kind of a variable, by key: this batch's or the mirror's.
type KindOf<'a> = dyn Fn(Key) -> Option<&'static str> + 'a;

/// Validates `batch` whole against the session; nothing is changed.
pub(crate) fn prepare(batch: Batch, view: &SessionView) -> Result<PreparedBatch, ServiceError> {
    let (new_kind, mut values) = new_variables(&batch, view)?;
    let kind_of = |key: Key| -> Option<&'static str> {
        new_kind
            .get(&key)
            .copied()
            .or_else(|| view.mirror.get(&key).map(|e| e.kind))
    };
    let mut factors = Vec::with_capacity(batch.factors.len());
    for (i, spec) in batch.factors.iter().enumerate() {
        in_time(view, i, batch.factors.len(), "building the factors")?;
        factors.push(prepare_factor(i, spec, view, &kind_of)?);
    }
    let predicted = predict_missing(&batch, &mut values, &factors, view)?;
    check_removals(&batch, view)?;
    let fix = fixes(&batch, &kind_of)?;
    let guesses = guesses(&batch, &kind_of)?;
    let variables: Vec<NewVariable> = batch
        .variables
        .iter()
        .zip(values)
        .map(|(spec, v)| NewVariable {
            key: spec.key,
            value: v.expect("predicted above"),
            fixed: spec.fixed,
            stamp: spec.stamp,
        })
        .collect();
    check_residuals(&factors, &variables, &guesses, view)?;
    Ok(PreparedBatch {
        variables,
        factors,
        remove: batch.remove_factors,
        fix,
        guesses,
        predicted,
        merges: Vec::new(),
    })
}

/// The batch's new variables: kind, uniqueness, value (when given). Returns the kind of each
/// and their values, in order.
#[allow(clippy::type_complexity)]
fn new_variables(
    batch: &Batch,
    view: &SessionView,
) -> Result<(HashMap<Key, &'static str>, Vec<Option<Box<dyn Variable>>>), ServiceError> {
    let kind = view.kind;
    let mut new_kind: HashMap<Key, &'static str> = HashMap::new();
    let mut values: Vec<Option<Box<dyn Variable>>> = Vec::with_capacity(batch.variables.len());
    for (i, spec) in batch.variables.iter().enumerate() {
        let field = |suffix: &str| format!("variables[{i}]{suffix}");
        let Some(&var_kind) = kind.variable_kinds.iter().find(|k| **k == spec.kind) else {
            return Err(ServiceError::bad_request(
                "wrong_kind",
                field(".kind"),
                format!(
                    "a {} session holds variables of kind {:?}, not `{}`",
                    kind.name, kind.variable_kinds, spec.kind
                ),
            ));
        };
        if view.mirror.contains_key(&spec.key) || new_kind.insert(spec.key, var_kind).is_some() {
            return Err(ServiceError::invalid(
                "duplicate_variable",
                field(".key"),
                format!("variable {} already exists", spec.key),
            ));
        }
        if let Some(stamp) = spec.stamp.filter(|s| !s.is_finite()) {
            return Err(ServiceError::bad_request(
                "non_finite",
                field(".stamp"),
                format!(
                    "{} is {stamp}, not a finite number of seconds",
                    field(".stamp")
                ),
            ));
        }
        values.push(match &spec.value {
            Some(v) => Some(decode_value(var_kind, v, &|| field(".value"))?),
            None => None,
        });
    }
    Ok((new_kind, values))
}

/// The batch's factor `i`: its type, keys, measurement, noise and robust kernel.
fn prepare_factor(
    i: usize,
    spec: &FactorSpec,
    view: &SessionView,
    kind_of: &KindOf,
) -> Result<PreparedFactor, ServiceError> {
    let kind = view.kind;
    let field = |suffix: &str| format!("factors[{i}]{suffix}");
    let codec = view
        .factor_types
        .resolve(kind, &spec.factor_type)
        .ok_or_else(|| {
            let mut accepted: Vec<&str> = kind.factor_types.to_vec();
            accepted.extend(view.factor_types.names().iter().map(String::as_str));
            ServiceError::bad_request(
                "unknown_factor_type",
                field(".type"),
                format!(
                    "a {} session accepts factors {accepted:?}, not `{}`",
                    kind.name, spec.factor_type
                ),
            )
        })?;
    check_factor_keys(spec, codec.name(), codec.variable_kinds(), kind_of, &field)?;
    if spec.measurement.len() != codec.measurement_len() {
        return Err(ServiceError::bad_request(
            "wrong_dimension",
            field(".measurement"),
            format!(
                "{} measurement has {} numbers, got {}",
                codec.name(),
                codec.measurement_len(),
                spec.measurement.len()
            ),
        ));
    }
    finite(&spec.measurement, &|| field(".measurement"))?;
    let factor = codec
        .build(&spec.keys, &spec.measurement)
        .map_err(|m| ServiceError::bad_request("invalid_value", field(".measurement"), m))?;
    let sqrt_information = information(spec, codec.residual_dim(), &|| field(""))?;
    if let Some(s) = spec.robust.map(|k| k.scale()) {
        if !robust::scale_in_range(s) {
            return Err(ServiceError::bad_request(
                "invalid_value",
                field(".robust.scale"),
                format!(
                    "robust kernel scale must be a number from {:e} to {:e}, got {s:e}",
                    robust::MIN_SCALE,
                    robust::MAX_SCALE
                ),
            ));
        }
    }
    let candidate = is_candidate(view.outliers, spec.outlier, codec.name(), &spec.keys);
    Ok(PreparedFactor {
        factor: factor.into(),
        sqrt_information,
        robust: spec.robust,
        candidate,
    })
}

/// A factor's keys: as many as its type connects, each once, each an existing variable of the
/// kind its type needs there.
fn check_factor_keys(
    spec: &FactorSpec,
    name: &str,
    expected_kinds: &[&'static str],
    kind_of: &KindOf,
    field: &dyn Fn(&str) -> String,
) -> Result<(), ServiceError> {
    if spec.keys.len() != expected_kinds.len() {
        return Err(ServiceError::bad_request(
            "wrong_dimension",
            field(".keys"),
            format!(
                "{name} connects {} variables, got {} keys",
                expected_kinds.len(),
                spec.keys.len()
            ),
        ));
    }
    for (k, (&key, &expected)) in spec.keys.iter().zip(expected_kinds).enumerate() {
        let key_field = || field(&format!(".keys[{k}]"));
        if spec.keys[..k].contains(&key) {
            return Err(ServiceError::bad_request(
                "repeated_variable",
                key_field(),
                format!("variable {key} appears twice"),
            ));
        }
        match kind_of(key) {
            None => {
                return Err(ServiceError::invalid(
                    "unknown_variable",
                    key_field(),
                    format!("variable {key} does not exist (add it in this or an earlier batch)"),
                ))
            }
            Some(found) if found != expected => {
                return Err(ServiceError::invalid(
                    "wrong_kind",
                    key_field(),
                    format!("{name} needs a {expected} here, variable {key} is a {found}"),
                ))
            }
            Some(_) => {}
        }
    }
    Ok(())
}

/// Every factor the batch removes is live, and removed once.
fn check_removals(batch: &Batch, view: &SessionView) -> Result<(), ServiceError> {
    let mut removed = HashSet::new();
    for (i, &id) in batch.remove_factors.iter().enumerate() {
        if !view.live_factors.contains(&id) || !removed.insert(id) {
            return Err(ServiceError::invalid(
                "unknown_factor",
                format!("remove_factors[{i}]"),
                format!("factor {id} does not exist (or is removed twice)"),
            ));
        }
    }
    Ok(())
}

/// Fix and unfix: existing (or this batch's) variables, none both.
fn fixes(batch: &Batch, kind_of: &KindOf) -> Result<Vec<(Key, bool)>, ServiceError> {
    let mut fix = Vec::new();
    for (list, fixed, name) in [(&batch.fix, true, "fix"), (&batch.unfix, false, "unfix")] {
        for (i, &key) in list.iter().enumerate() {
            if kind_of(key).is_none() {
                return Err(ServiceError::invalid(
                    "unknown_variable",
                    format!("{name}[{i}]"),
                    format!("variable {key} does not exist"),
                ));
            }
            if !fixed && batch.fix.contains(&key) {
                return Err(ServiceError::bad_request(
                    "conflicting_fix",
                    format!("unfix[{i}]"),
                    format!("variable {key} is both fixed and unfixed"),
                ));
            }
            fix.push((key, fixed));
        }
    }
    Ok(fix)
}

/// Guesses for existing (or this batch's) variables, decoded.
#[allow(clippy::type_complexity)]
fn guesses(batch: &Batch, kind_of: &KindOf) -> Result<Vec<(Key, Box<dyn Variable>)>, ServiceError> {
    let mut guesses = Vec::with_capacity(batch.guesses.len());
    for (i, g) in batch.guesses.iter().enumerate() {
        let field = |suffix: &str| format!("guesses[{i}]{suffix}");
        let Some(var_kind) = kind_of(g.key) else {
            return Err(ServiceError::invalid(
                "unknown_variable",
                field(".key"),
                format!("variable {} does not exist", g.key),
            ));
        };
        guesses.push((
            g.key,
            decode_value(var_kind, &g.value, &|| field(".value"))?,
        ));
    }
    Ok(guesses)
}

/// Every new factor must have a finite residual at its start values (a camera looking at a
/// point in its own centre, poses at 1e308): the solver could do nothing with it.
fn check_residuals(
    factors: &[PreparedFactor],
    variables: &[NewVariable],
    guesses: &[(Key, Box<dyn Variable>)],
    view: &SessionView,
) -> Result<(), ServiceError> {
    // The value each key starts from: a guess (the last one wins), else the batch's new
    // variable; mirror values are decoded on first use.
    let mut given: HashMap<Key, &dyn Variable> = HashMap::new();
    for v in variables {
        given.insert(v.key, v.value.as_ref());
    }
    for (key, v) in guesses {
        given.insert(*key, v.as_ref());
    }
    let mut decoded: HashMap<Key, Box<dyn Variable>> = HashMap::new();
    for f in factors {
        for key in f.factor.keys() {
            if !given.contains_key(key) && !decoded.contains_key(key) {
                let entry = view.mirror.get(key).expect("keys were checked above");
                decoded.insert(*key, entry.decode());
            }
        }
    }
    for (i, f) in factors.iter().enumerate() {
        in_time(view, i, factors.len(), "checking the residuals")?;
        let vars: Vec<&dyn Variable> = f
            .factor
            .keys()
            .iter()
            .map(|key| {
                given
                    .get(key)
                    .copied()
                    .unwrap_or_else(|| decoded[key].as_ref())
            })
            .collect();
        if !crate::factors::cost_is_finite(f.factor.as_ref(), &f.sqrt_information, &vars) {
            return Err(ServiceError::invalid(
                "non_finite_residual",
                format!("factors[{i}]"),
                "the factor's residual or its weighted cost is not finite at the values it \
                 would start from (a point at a camera's centre, values so large they overflow)",
            ));
        }
    }
    Ok(())
}

/// Fills in values the client left out, walking the batch's factors outwards from known
/// variables (existing, or new with a value): an odometry chain is predicted in one pass.
fn predict_missing(
    batch: &Batch,
    values: &mut [Option<Box<dyn Variable>>],
    factors: &[PreparedFactor],
    view: &SessionView,
) -> Result<Vec<Key>, ServiceError> {
    let mut predicted = Vec::new();
    if values.iter().all(Option::is_some) {
        return Ok(predicted);
    }
    let position: HashMap<Key, usize> = batch
        .variables
        .iter()
        .enumerate()
        .map(|(i, v)| (v.key, i))
        .collect();
    // Existing variables that the factors touch, decoded once.
    let mut existing: HashMap<Key, Box<dyn Variable>> = HashMap::new();
    for f in factors {
        for &key in f.factor.keys() {
            if let (None, Some(entry)) = (position.get(&key), view.mirror.get(&key)) {
                existing.entry(key).or_insert_with(|| entry.decode());
            }
        }
    }
    loop {
        let mut progress = false;
        for f in factors {
            let keys = f.factor.keys();
            let missing: Vec<usize> = (0..keys.len())
                .filter(|&k| position.get(&keys[k]).is_some_and(|&p| values[p].is_none()))
                .collect();
            let [target] = missing[..] else { continue };
            let known: Vec<Option<&dyn Variable>> = keys
                .iter()
                .enumerate()
                .map(|(k, key)| {
                    if k == target {
                        return None;
                    }
                    match position.get(key) {
                        Some(&p) => values[p].as_deref(),
                        None => existing.get(key).map(|v| v.as_ref()),
                    }
                })
                .collect();
            if let Some(v) = f.factor.predict(&known, target) {
                let p = position[&keys[target]];
                values[p] = Some(v);
                predicted.push(keys[target]);
                progress = true;
            }
        }
        if !progress {
            break;
        }
    }
    match values.iter().position(Option::is_none) {
        Some(i) => Err(ServiceError::invalid(
            "missing_value",
            format!("variables[{i}].value"),
            format!(
                "variable {} has no value and no factor in the batch connects it to a known variable",
                batch.variables[i].key
            ),
        )),
        None => Ok(predicted),
    }
}
