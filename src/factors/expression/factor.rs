//! A compiled factor type and the factors it builds.

use std::cell::RefCell;
use std::collections::HashMap;
use std::sync::Arc;

use nalgebra::{Matrix3, UnitQuaternion, Vector3};

use super::builder::{Builder, Typed};
use super::lower::Lowering;
use super::tape::{Op, Scratch, Seeds, Slot, Tape};
use super::{
    DefinitionError, FactorTypeDefinition, MAX_COST, MAX_MEASUREMENT, MAX_PARAMETERS, MAX_RESIDUAL,
    MAX_VARIABLES,
};
use crate::factors::{EvaluationError, Factor};
use crate::geometry::{so3, Point2, Point3, Se2, Se3, SnavelyCamera};
use crate::variables::{Key, Variable};

/// A declared kind: how many tape inputs it lowers to and its tangent dimension.
#[derive(Debug)]
struct KindLayout {
    kind: &'static str,
    seed: SeedKind,
    inputs: usize,
    tangent: usize,
}

/// How a kind's values and retraction become tape inputs (matched per evaluation, so not by
/// name).
#[derive(Debug, Clone, Copy)]
enum SeedKind {
    Se2,
    Se3,
    Point2,
    Point3,
    Camera,
}

const VARIABLE_KINDS: &[KindLayout] = &[
    KindLayout {
        kind: "se2",
        seed: SeedKind::Se2,
        inputs: 3,
        tangent: 3,
    },
    KindLayout {
        kind: "se3",
        seed: SeedKind::Se3,
        inputs: 12,
        tangent: 6,
    },
    KindLayout {
        kind: "point2",
        seed: SeedKind::Point2,
        inputs: 2,
        tangent: 2,
    },
    KindLayout {
        kind: "point3",
        seed: SeedKind::Point3,
        inputs: 3,
        tangent: 3,
    },
    KindLayout {
        kind: "snavely_camera",
        seed: SeedKind::Camera,
        inputs: 15,
        tangent: 9,
    },
];

/// A parameter's kind: its wire length and its length on the tape.
#[derive(Clone, Copy, Debug)]
pub(super) enum ParamKind {
    Scalar,
    Vector(usize),
    Se2,
    Se3,
}

impl ParamKind {
    pub(super) fn wire_len(self) -> usize {
        match self {
            ParamKind::Scalar => 1,
            ParamKind::Vector(n) => n,
            ParamKind::Se2 => 3,
            ParamKind::Se3 => 7,
        }
    }
    fn tape_len(self) -> usize {
        match self {
            ParamKind::Se3 => 12,
            other => other.wire_len(),
        }
    }
}

/// A factor type compiled from a [`FactorTypeDefinition`]; shared by the factors it builds.
#[derive(Debug)]
pub struct ExpressionType {
    pub definition: FactorTypeDefinition,
    kinds: Vec<&'static str>,
    /// The layout of each variable, by position (looked up once, not per evaluation).
    layouts: Vec<&'static KindLayout>,
    /// Number of tape inputs.
    inputs: usize,
    params: Vec<ParamKind>,
    measurement_len: usize,
    tape: Tape,
    /// Whether each slot depends on neither a variable nor a parameter.
    constant: Vec<bool>,
    /// Sum of the variables' tangent dimensions: the dual numbers' width.
    lanes: usize,
    /// For error reports: the node each slot came from. Like `constant`, only the checks at
    /// compile time read it: emptied once they pass (about a tenth of a large type's memory).
    origin: Vec<u32>,
    paths: Vec<String>,
    /// What it holds, estimated once compiled ([`ExpressionType::memory_bytes`]).
    memory_bytes: usize,
}

thread_local! {
    static SCRATCH: RefCell<(Seeds, Scratch)> = RefCell::new((
        Seeds { values: Vec::new(), gradients: Vec::new() },
        Scratch::default(),
    ));
}

fn refuse(path: impl Into<String>, message: impl Into<String>) -> DefinitionError {
    DefinitionError {
        path: path.into(),
        message: message.into(),
    }
}

fn valid_name(name: &str) -> bool {
    (1..=64).contains(&name.len())
        && name.starts_with(|c: char| c.is_ascii_lowercase())
        && name
            .chars()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_')
}

impl ExpressionType {
    /// Type-checks, lowers, bounds and numerically checks a definition.
    pub fn compile(definition: FactorTypeDefinition) -> Result<Arc<Self>, DefinitionError> {
        if !valid_name(&definition.name) {
            return Err(refuse(
                "name",
                "1-64 characters of [a-z0-9_], starting with a letter",
            ));
        }
        if definition.variables.is_empty() || definition.variables.len() > MAX_VARIABLES {
            return Err(refuse(
                "variables",
                format!("1 to {MAX_VARIABLES} variables"),
            ));
        }
        if definition.parameters.len() > MAX_PARAMETERS {
            return Err(refuse(
                "parameters",
                format!("at most {MAX_PARAMETERS} parameters"),
            ));
        }
        let mut builder = Builder::default();
        let mut names: HashMap<String, Typed> = HashMap::new();
        let mut kinds = Vec::new();
        let mut lanes = 0;
        let mut input = 0u32;
        for (i, v) in definition.variables.iter().enumerate() {
            let path = format!("variables[{i}]");
            let Some(layout) = VARIABLE_KINDS.iter().find(|k| k.kind == v.kind) else {
                let known: Vec<_> = VARIABLE_KINDS.iter().map(|k| k.kind).collect();
                return Err(refuse(
                    format!("{path}.kind"),
                    format!("unknown kind `{}` (known: {known:?})", v.kind),
                ));
            };
            if v.len.is_some() {
                return Err(refuse(
                    format!("{path}.len"),
                    "only `vector` parameters take a length",
                ));
            }
            builder.enter(&path);
            let slots: Vec<Slot> = (0..layout.inputs)
                .map(|k| builder.push(Op::Input(input + k as u32)))
                .collect();
            input += layout.inputs as u32;
            declare(&mut names, &v.name, &path, typed_from(layout.kind, &slots))?;
            kinds.push(layout.kind);
            lanes += layout.tangent;
        }
        let mut params = Vec::new();
        let mut param_slot = 0u32;
        for (i, p) in definition.parameters.iter().enumerate() {
            let path = format!("parameters[{i}]");
            let kind = match (p.kind.as_str(), p.len) {
                ("scalar", None) => ParamKind::Scalar,
                ("vector", Some(n)) if (1..=MAX_MEASUREMENT).contains(&n) => ParamKind::Vector(n),
                ("vector", _) => return Err(refuse(format!("{path}.len"), format!("a vector parameter needs a len of 1 to {MAX_MEASUREMENT}"))),
                ("point2", None) => ParamKind::Vector(2),
                ("point3", None) => ParamKind::Vector(3),
                ("se2", None) => ParamKind::Se2,
                ("se3", None) => ParamKind::Se3,
                (_, Some(_)) => return Err(refuse(format!("{path}.len"), "only `vector` parameters take a length")),
                (other, None) => {
                    return Err(refuse(
                        format!("{path}.kind"),
                        format!("unknown parameter kind `{other}` (known: scalar, vector, point2, point3, se2, se3)"),
                    ))
                }
            };
            builder.enter(&path);
            let slots: Vec<Slot> = (0..kind.tape_len())
                .map(|k| builder.push(Op::Param(param_slot + k as u32)))
                .collect();
            param_slot += kind.tape_len() as u32;
            let typed = match kind {
                ParamKind::Scalar => Typed::Scalar(slots[0]),
                ParamKind::Vector(_) => Typed::Vector(slots),
                ParamKind::Se2 => typed_from("se2", &slots),
                ParamKind::Se3 => typed_from("se3", &slots),
            };
            declare(&mut names, &p.name, &path, typed)?;
            params.push(kind);
        }
        let measurement_len: usize = params.iter().map(|p| p.wire_len()).sum();
        if measurement_len > MAX_MEASUREMENT {
            return Err(refuse(
                "parameters",
                format!("the measurement has {measurement_len} numbers, at most {MAX_MEASUREMENT}"),
            ));
        }
        let residual = Lowering {
            builder: &mut builder,
            names: &names,
            nodes: 0,
        }
        .lower(&definition.residual, "residual", 0)?;
        let outputs = match residual {
            Typed::Scalar(s) => vec![s],
            Typed::Vector(v) => v,
            other => {
                return Err(refuse(
                    "residual",
                    format!(
                        "the residual is a scalar or a vector, not a {}",
                        other.type_name()
                    ),
                ))
            }
        };
        if outputs.len() > MAX_RESIDUAL {
            return Err(refuse(
                "residual",
                format!(
                    "the residual has {} entries, at most {MAX_RESIDUAL}",
                    outputs.len()
                ),
            ));
        }
        if let Some(dim) = definition.residual_dim.filter(|&d| d != outputs.len()) {
            return Err(refuse(
                "residual_dim",
                format!("is {dim} but the residual has {} entries", outputs.len()),
            ));
        }
        let cost = builder.len() * (1 + lanes);
        if cost > MAX_COST {
            return Err(refuse(
                "residual",
                format!("the expression compiles to {} operations x {} derivatives, over the bound of {MAX_COST}", builder.len(), 1 + lanes),
            ));
        }
        let (tape, constant, origin, paths) = builder.finish(outputs);
        let mut compiled = Arc::new(Self {
            definition,
            layouts: kinds.iter().map(|k| layout(k)).collect(),
            inputs: input as usize,
            kinds,
            params,
            measurement_len,
            tape,
            constant,
            lanes,
            origin,
            paths,
            memory_bytes: 0,
        });
        super::check::check(&compiled)?;
        let ty = Arc::get_mut(&mut compiled).expect("the checks keep no reference");
        ty.constant = Vec::new();
        ty.origin = Vec::new();
        ty.paths = Vec::new();
        ty.memory_bytes = super::memory::type_bytes(
            std::mem::size_of::<Self>(),
            &ty.definition,
            ty.tape.heap_bytes(),
            ty.kinds.capacity() * std::mem::size_of::<&str>()
                + ty.layouts.capacity() * std::mem::size_of::<&KindLayout>()
                + ty.params.capacity() * std::mem::size_of::<ParamKind>(),
        );
        Ok(compiled)
    }

    /// Estimated bytes this compiled type holds: its tape, its definition (kept for creation
    /// records and snapshots) and the rest, from their sizes. What each session that declares it
    /// is charged; shared types count once in the server's total (see `interner`).
    pub fn memory_bytes(&self) -> usize {
        self.memory_bytes
    }

    pub fn name(&self) -> &str {
        &self.definition.name
    }
    pub fn variable_kinds(&self) -> &[&'static str] {
        &self.kinds
    }
    pub fn measurement_len(&self) -> usize {
        self.measurement_len
    }
    pub fn residual_dim(&self) -> usize {
        self.tape.outputs.len()
    }
    /// Operations on the tape, and how many of them an evaluation runs (those that depend on
    /// a variable).
    pub fn operations(&self) -> (usize, usize) {
        (self.tape.ops.len(), self.tape.varying_operations())
    }
    pub(super) fn path_of(&self, slot: Slot) -> &str {
        &self.paths[self.origin[slot as usize] as usize]
    }
    pub(super) fn parameter_kinds(&self) -> &[ParamKind] {
        &self.params
    }
    /// Number of tape parameters (the measurement with `se3` as a matrix and a translation).
    pub(super) fn tape_parameters(&self) -> usize {
        self.params.iter().map(|p| p.tape_len()).sum()
    }
    /// Evaluates once with every input and parameter zero; the first slot that depends on
    /// neither and is not finite (`log(0)`, `1/0`) is wrong at any values.
    pub(super) fn first_constant_non_finite(&self) -> Option<Slot> {
        SCRATCH.with(|cell| {
            let (_, scratch) = &mut *cell.borrow_mut();
            self.tape
                .fixed_part(&vec![0.0; self.tape_parameters()], scratch);
            (0..self.constant.len() as Slot)
                .find(|&s| self.constant[s as usize] && !scratch.value(s).is_finite())
        })
    }

    /// A factor of this type between `keys` (count checked by the caller) with the wire
    /// measurement `measurement` (length checked), or why the measurement is invalid.
    pub fn build(
        self: &Arc<Self>,
        keys: &[Key],
        measurement: &[f64],
    ) -> Result<ExpressionFactor, String> {
        let mut params = Vec::with_capacity(self.tape.outputs.len());
        let mut at = 0;
        for (i, kind) in self.params.iter().enumerate() {
            let wire = &measurement[at..at + kind.wire_len()];
            at += kind.wire_len();
            match kind {
                ParamKind::Se3 => {
                    let pose = crate::variables::se3::decode_se3(wire).map_err(|m| {
                        format!("parameter `{}`: {m}", self.definition.parameters[i].name)
                    })?;
                    push_se3(&mut params, &pose.rotation, &pose.translation);
                }
                _ => params.extend_from_slice(wire),
            }
        }
        Ok(self.with_parameters(keys, params))
    }

    /// A factor with its measurement already lowered to tape parameters.
    pub(super) fn with_parameters(
        self: &Arc<Self>,
        keys: &[Key],
        params: Vec<f64>,
    ) -> ExpressionFactor {
        let fixed = SCRATCH.with(|cell| self.tape.fixed_part(&params, &mut cell.borrow_mut().1));
        ExpressionFactor {
            ty: Arc::clone(self),
            keys: keys.to_vec(),
            fixed,
        }
    }

    /// Evaluates at `variables` with a factor's `fixed` values; returns the first non-finite
    /// slot, if any.
    pub(super) fn evaluate_at(
        &self,
        variables: &[&dyn Variable],
        fixed: &[f64],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<Option<Slot>, EvaluationError> {
        SCRATCH.with(|cell| {
            let (seeds, scratch) = &mut *cell.borrow_mut();
            self.seed(variables, seeds, jacobian.is_some())?;
            self.tape
                .evaluate(seeds, fixed, self.lanes, scratch, error, jacobian);
            Ok(if error.iter().all(|v| v.is_finite()) {
                None
            } else {
                self.tape.first_non_finite(scratch)
            })
        })
    }

    /// Writes the variables' values as tape inputs and, with `gradients`, the first-order terms
    /// of their retractions as the inputs' gradient rows.
    fn seed(
        &self,
        variables: &[&dyn Variable],
        seeds: &mut Seeds,
        gradients: bool,
    ) -> Result<(), EvaluationError> {
        seeds.values.clear();
        if gradients {
            seeds.gradients.clear();
            seeds.gradients.resize(self.inputs * self.lanes, 0.0);
        }
        let lanes = self.lanes;
        let mut lane = 0;
        for (position, layout) in self.layouts.iter().enumerate() {
            let kind = layout.kind;
            let first = seeds.values.len();
            // Row `first + row` of the gradients, column `lane + col`.
            let set = |g: &mut Vec<f64>, row: usize, col: usize, v: f64| {
                g[(first + row) * lanes + lane + col] = v
            };
            match layout.seed {
                SeedKind::Se2 => {
                    let p: &Se2 = crate::factors::expect_kind(variables, position, kind)?;
                    seeds.values.extend_from_slice(&[p.x, p.y, p.theta]);
                    if gradients {
                        (0..3).for_each(|k| set(&mut seeds.gradients, k, k, 1.0));
                    }
                }
                SeedKind::Point2 => {
                    let p: &Point2 = crate::factors::expect_kind(variables, position, kind)?;
                    seeds.values.extend_from_slice(p.0.as_slice());
                    if gradients {
                        (0..2).for_each(|k| set(&mut seeds.gradients, k, k, 1.0));
                    }
                }
                SeedKind::Point3 => {
                    let p: &Point3 = crate::factors::expect_kind(variables, position, kind)?;
                    seeds.values.extend_from_slice(p.0.as_slice());
                    if gradients {
                        (0..3).for_each(|k| set(&mut seeds.gradients, k, k, 1.0));
                    }
                }
                SeedKind::Se3 => {
                    // (R Exp(ω), t + R v): ∂R/∂ω_m = R [e_m]×, ∂t/∂v = R.
                    let p: &Se3 = crate::factors::expect_kind(variables, position, kind)?;
                    let r = push_se3(&mut seeds.values, &p.rotation, &p.translation);
                    if gradients {
                        for m in 0..3 {
                            let d = r * so3::hat(&Vector3::ith(m, 1.0));
                            (0..9).for_each(|k| {
                                set(&mut seeds.gradients, k, 3 + m, d[(k / 3, k % 3)])
                            });
                            (0..3).for_each(|k| set(&mut seeds.gradients, 9 + k, m, r[(k, m)]));
                        }
                    }
                }
                SeedKind::Camera => {
                    // (Exp(ω) R, t + δt, [f, k1, k2] + δk): ∂R/∂ω_m = [e_m]× R.
                    let c: &SnavelyCamera = crate::factors::expect_kind(variables, position, kind)?;
                    let r = push_se3(&mut seeds.values, &c.rotation, &c.translation);
                    seeds.values.extend_from_slice(&[c.focal, c.k1, c.k2]);
                    if gradients {
                        for m in 0..3 {
                            let d = so3::hat(&Vector3::ith(m, 1.0)) * r;
                            (0..9).for_each(|k| set(&mut seeds.gradients, k, m, d[(k / 3, k % 3)]));
                        }
                        (0..6).for_each(|k| set(&mut seeds.gradients, 9 + k, 3 + k, 1.0));
                    }
                }
            }
            lane += layout.tangent;
        }
        Ok(())
    }
}

fn layout(kind: &str) -> &'static KindLayout {
    VARIABLE_KINDS
        .iter()
        .find(|k| k.kind == kind)
        .expect("kinds are checked at compile time")
}

/// Appends `R` (row-major) and `t`; returns `R`.
pub(super) fn push_se3(
    out: &mut Vec<f64>,
    rotation: &UnitQuaternion<f64>,
    translation: &Vector3<f64>,
) -> Matrix3<f64> {
    let r = rotation.to_rotation_matrix().into_inner();
    for k in 0..9 {
        out.push(r[(k / 3, k % 3)]);
    }
    out.extend_from_slice(translation.as_slice());
    r
}

/// The typed value of a kind's slots (`se2`: 3, `se3`: 12, points, camera: 15).
fn typed_from(kind: &str, s: &[Slot]) -> Typed {
    let r = |o: usize| -> [Slot; 9] { std::array::from_fn(|k| s[o + k]) };
    let v3 = |o: usize| -> [Slot; 3] { std::array::from_fn(|k| s[o + k]) };
    match kind {
        "se2" => Typed::Se2(v3(0)),
        "se3" => Typed::Se3(r(0), v3(9)),
        "snavely_camera" => Typed::Camera(r(0), v3(9), v3(12)),
        _ => Typed::Vector(s.to_vec()),
    }
}

fn declare(
    names: &mut HashMap<String, Typed>,
    name: &str,
    path: &str,
    typed: Typed,
) -> Result<(), DefinitionError> {
    if !valid_name(name) {
        return Err(refuse(
            format!("{path}.name"),
            "1-64 characters of [a-z0-9_], starting with a letter",
        ));
    }
    if names.insert(name.to_string(), typed).is_some() {
        return Err(refuse(
            format!("{path}.name"),
            format!("`{name}` is declared twice"),
        ));
    }
    Ok(())
}

/// A factor of a user-defined type.
#[derive(Clone, Debug)]
pub struct ExpressionFactor {
    ty: Arc<ExpressionType>,
    keys: Vec<Key>,
    /// What its measurement determines before any variable is known: the tape's frontier
    /// values (see [`Tape::fixed_part`]).
    fixed: Vec<f64>,
}

impl ExpressionFactor {
    pub fn expression_type(&self) -> &Arc<ExpressionType> {
        &self.ty
    }
    pub(super) fn fixed(&self) -> &[f64] {
        &self.fixed
    }
}

impl Factor for ExpressionFactor {
    fn name(&self) -> &str {
        self.ty.name()
    }
    fn keys(&self) -> &[Key] {
        &self.keys
    }
    fn residual_dim(&self) -> usize {
        self.ty.residual_dim()
    }
    fn variable_kinds(&self) -> &[&'static str] {
        &self.ty.kinds
    }
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        self.ty
            .evaluate_at(variables, &self.fixed, error, jacobian)
            .map(|_| ())
    }
    fn as_any(&self) -> &dyn std::any::Any {
        self
    }
}
