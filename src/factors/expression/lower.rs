//! Reading an expression (a JSON tree) into tape operations, checking types on the way.
//!
//! The language, node by node:
//! - a number is a scalar constant;
//! - a string names a variable or a parameter of the definition;
//! - an array is a vector: its elements are scalars or vectors, concatenated;
//! - an object with one key is an operation, `{"op": [arguments…]}`.
//!
//! Every error names the node by its path from the residual: `residual.compose[1].inverse[0]`.

use std::collections::HashMap;

use serde_json::Value;

use super::builder::{Builder, Typed};
use super::tape::{Op, Slot};
use super::DefinitionError;

/// Every operation with its argument count and the signatures it accepts (for errors and docs).
pub const OPERATIONS: &[(&str, usize, &str)] = &[
    ("add", 2, "(scalar, scalar) | (vectorN, vectorN)"),
    ("sub", 2, "(scalar, scalar) | (vectorN, vectorN)"),
    (
        "mul",
        2,
        "(scalar, scalar) | (scalar, vectorN) | (vectorN, scalar)",
    ),
    ("div", 2, "(scalar, scalar) | (vectorN, scalar)"),
    ("neg", 1, "scalar | vectorN"),
    ("sin", 1, "scalar"),
    ("cos", 1, "scalar"),
    ("tan", 1, "scalar"),
    ("asin", 1, "scalar"),
    ("acos", 1, "scalar"),
    ("atan", 1, "scalar"),
    ("atan2", 2, "(y: scalar, x: scalar)"),
    ("sqrt", 1, "scalar"),
    ("exp", 1, "scalar"),
    ("abs", 1, "scalar"),
    ("pow", 2, "(scalar, scalar)"),
    ("wrap", 1, "scalar: the angle in (-pi, pi]"),
    (
        "log",
        1,
        "scalar (natural log) | so3 -> vector3 | se2 -> vector3 [V^-1 t, theta]",
    ),
    ("dot", 2, "(vectorN, vectorN)"),
    ("cross", 2, "(vector3, vector3)"),
    ("norm", 1, "vectorN"),
    ("squared_norm", 1, "vectorN"),
    ("at", 2, "(vectorN, integer literal)"),
    ("compose", 2, "(se2, se2) | (so3, so3) | (se3, se3)"),
    ("inverse", 1, "se2 | so3 | se3"),
    ("between", 2, "(a, b) -> a^-1 b for se2, so3, se3"),
    (
        "act",
        2,
        "(se2, vector2) | (so3, vector3) | (se3, vector3): R p + t",
    ),
    (
        "translation",
        1,
        "se2 -> vector2 | se3 -> vector3 | snavely_camera -> vector3",
    ),
    ("rotation", 1, "se3 -> so3 | snavely_camera -> so3"),
    ("angle", 1, "se2 -> scalar (not wrapped)"),
    ("intrinsics", 1, "snavely_camera -> vector3 [f, k1, k2]"),
    ("exp_so3", 1, "vector3 -> so3"),
    ("exp_se2", 1, "vector3 [u, theta] -> se2"),
    ("se2", 3, "(x: scalar, y: scalar, theta: scalar)"),
    ("se3", 2, "(so3, vector3)"),
];

/// Bounds on a definition: nodes read and nesting depth.
pub const MAX_NODES: usize = 4096;
/// An operation node is two JSON levels (`{"inverse": [x]}`) and JSON parsers stop at 128
/// levels (serde_json's recursion limit), counting the request, journal record or snapshot
/// around the definition too: 48 keeps every definition this accepts readable wherever it is
/// carried, so a deeper one gets this rule's error, not `malformed_json`.
pub const MAX_DEPTH: usize = 48;

pub(super) struct Lowering<'a> {
    pub builder: &'a mut Builder,
    pub names: &'a HashMap<String, Typed>,
    pub nodes: usize,
}

fn error(path: &str, message: impl Into<String>) -> DefinitionError {
    DefinitionError {
        path: path.to_string(),
        message: message.into(),
    }
}

impl Lowering<'_> {
    pub fn lower(
        &mut self,
        node: &Value,
        path: &str,
        depth: usize,
    ) -> Result<Typed, DefinitionError> {
        self.nodes += 1;
        if self.nodes > MAX_NODES {
            return Err(error(
                path,
                format!("the expression has more than {MAX_NODES} nodes"),
            ));
        }
        if depth > MAX_DEPTH {
            return Err(error(
                path,
                format!("the expression nests deeper than {MAX_DEPTH} levels"),
            ));
        }
        self.builder.enter(path);
        match node {
            Value::Number(n) => match n.as_f64().filter(|v| v.is_finite()) {
                Some(v) => Ok(Typed::Scalar(self.builder.constant_value(v))),
                None => Err(error(path, format!("{n} is not a finite number"))),
            },
            Value::String(name) => self.names.get(name).cloned().ok_or_else(|| {
                let mut known: Vec<&String> = self.names.keys().collect();
                known.sort();
                error(
                    path,
                    format!("unknown name `{name}` (variables and parameters: {known:?})"),
                )
            }),
            Value::Array(items) => self.vector(items, path, depth),
            Value::Object(map) => {
                let mut entries = map.iter();
                let (Some((op, args)), None) = (entries.next(), entries.next()) else {
                    return Err(error(
                        path,
                        "an operation is an object with exactly one key, its name: {\"sin\": [x]}",
                    ));
                };
                self.operation(op, args, &format!("{path}.{op}"), depth)
            }
            Value::Bool(_) | Value::Null => Err(error(
                path,
                "expected a number, a name, an array (vector) or an operation object",
            )),
        }
    }

    fn vector(
        &mut self,
        items: &[Value],
        path: &str,
        depth: usize,
    ) -> Result<Typed, DefinitionError> {
        if items.is_empty() {
            return Err(error(path, "an empty vector"));
        }
        let mut slots = Vec::new();
        for (k, item) in items.iter().enumerate() {
            let item_path = format!("{path}[{k}]");
            match self.lower(item, &item_path, depth + 1)? {
                Typed::Scalar(s) => slots.push(s),
                Typed::Vector(v) => slots.extend(v),
                other => {
                    return Err(error(
                        &item_path,
                        format!(
                            "a vector holds scalars and vectors, not a {}",
                            other.type_name()
                        ),
                    ))
                }
            }
        }
        Ok(Typed::Vector(slots))
    }

    fn operation(
        &mut self,
        op: &str,
        args: &Value,
        path: &str,
        depth: usize,
    ) -> Result<Typed, DefinitionError> {
        let Some(&(_, arity, signature)) = OPERATIONS.iter().find(|(name, ..)| *name == op) else {
            let known: Vec<&str> = OPERATIONS.iter().map(|(name, ..)| *name).collect();
            return Err(error(
                path,
                format!("unknown operation `{op}` (known: {known:?})"),
            ));
        };
        let Value::Array(args) = args else {
            return Err(error(
                path,
                format!("the arguments of `{op}` are an array: {{\"{op}\": [..]}}"),
            ));
        };
        if args.len() != arity {
            return Err(error(
                path,
                format!("`{op}` takes {arity} argument(s), got {}", args.len()),
            ));
        }
        if op == "at" {
            return self.at(args, path, depth);
        }
        let mut typed = Vec::with_capacity(args.len());
        for (k, a) in args.iter().enumerate() {
            typed.push(self.lower(a, &format!("{path}[{k}]"), depth + 1)?);
        }
        // Slots made from here on belong to this operation's node.
        self.builder.enter(path);
        self.apply(op, &typed).ok_or_else(|| {
            let got: Vec<String> = typed.iter().map(Typed::type_name).collect();
            error(
                path,
                format!("`{op}` takes {signature}, got ({})", got.join(", ")),
            )
        })
    }

    fn at(&mut self, args: &[Value], path: &str, depth: usize) -> Result<Typed, DefinitionError> {
        let vector = self.lower(&args[0], &format!("{path}[0]"), depth + 1)?;
        let index_path = format!("{path}[1]");
        let Some(index) = args[1].as_u64() else {
            return Err(error(
                &index_path,
                "the index is a non-negative integer literal",
            ));
        };
        match vector {
            Typed::Vector(v) => v
                .get(index as usize)
                .map(|&s| Typed::Scalar(s))
                .ok_or_else(|| {
                    error(
                        &index_path,
                        format!("index {index} is outside a vector of {}", v.len()),
                    )
                }),
            other => Err(error(
                &format!("{path}[0]"),
                format!("`at` indexes a vector, not a {}", other.type_name()),
            )),
        }
    }

    /// The operation on typed arguments, or `None` when the types do not fit.
    fn apply(&mut self, op: &str, args: &[Typed]) -> Option<Typed> {
        use Typed::*;
        let b = &mut *self.builder;
        let unary = |b: &mut Builder, f: fn(Slot) -> Op, a: Slot| Some(Scalar(b.push(f(a))));
        Some(match (op, args) {
            ("add", [Scalar(x), Scalar(y)]) => Scalar(b.add(*x, *y)),
            ("sub", [Scalar(x), Scalar(y)]) => Scalar(b.sub(*x, *y)),
            ("add" | "sub", [Vector(x), Vector(y)]) if x.len() == y.len() => Vector(
                x.iter()
                    .zip(y)
                    .map(|(&p, &q)| {
                        if op == "add" {
                            b.add(p, q)
                        } else {
                            b.sub(p, q)
                        }
                    })
                    .collect(),
            ),
            ("mul", [Scalar(x), Scalar(y)]) => Scalar(b.mul(*x, *y)),
            ("mul", [Scalar(s), Vector(v)]) | ("mul", [Vector(v), Scalar(s)]) => {
                Vector(v.iter().map(|&p| b.mul(*s, p)).collect())
            }
            ("div", [Scalar(x), Scalar(y)]) => Scalar(b.push(Op::Div(*x, *y))),
            ("div", [Vector(v), Scalar(s)]) => {
                Vector(v.iter().map(|&p| b.push(Op::Div(p, *s))).collect())
            }
            ("neg", [Scalar(x)]) => Scalar(b.neg(*x)),
            ("neg", [Vector(v)]) => Vector(v.iter().map(|&p| b.neg(p)).collect()),
            ("sin", [Scalar(x)]) => Scalar(b.sin(*x)),
            ("cos", [Scalar(x)]) => Scalar(b.cos(*x)),
            ("tan", [Scalar(x)]) => return unary(b, Op::Tan, *x),
            ("asin", [Scalar(x)]) => return unary(b, Op::Asin, *x),
            ("acos", [Scalar(x)]) => return unary(b, Op::Acos, *x),
            ("atan", [Scalar(x)]) => return unary(b, Op::Atan, *x),
            ("sqrt", [Scalar(x)]) => return unary(b, Op::Sqrt, *x),
            ("exp", [Scalar(x)]) => return unary(b, Op::Exp, *x),
            ("abs", [Scalar(x)]) => return unary(b, Op::Abs, *x),
            ("wrap", [Scalar(x)]) => return unary(b, Op::Wrap, *x),
            ("log", [Scalar(x)]) => return unary(b, Op::Ln, *x),
            ("atan2", [Scalar(y), Scalar(x)]) => Scalar(b.push(Op::Atan2(*y, *x))),
            ("pow", [Scalar(x), Scalar(y)]) => Scalar(b.push(Op::Pow(*x, *y))),
            ("log", [So3(r)]) => Vector(b.so3_log(*r).to_vec()),
            ("log", [Se2(a)]) => Vector(b.se2_log(*a).to_vec()),
            ("dot", [Vector(x), Vector(y)]) if x.len() == y.len() => Scalar(b.dot(x, y)),
            ("cross", [Vector(x), Vector(y)]) if x.len() == 3 && y.len() == 3 => {
                let mut c = Vec::with_capacity(3);
                for (i, j) in [(1, 2), (2, 0), (0, 1)] {
                    let (p, q) = (b.mul(x[i], y[j]), b.mul(x[j], y[i]));
                    c.push(b.sub(p, q));
                }
                Vector(c)
            }
            ("squared_norm", [Vector(x)]) => Scalar(b.dot(x, x)),
            ("norm", [Vector(x)]) => {
                let s = b.dot(x, x);
                Scalar(b.push(Op::Sqrt(s)))
            }
            ("compose", [Se2(x), Se2(y)]) => Se2(b.se2_compose(*x, *y)),
            ("compose", [So3(x), So3(y)]) => So3(b.so3_mul(*x, *y)),
            ("compose", [Se3(r, t), Se3(q, u)]) => {
                let (r, t) = b.se3_compose((*r, *t), (*q, *u));
                Se3(r, t)
            }
            ("inverse", [Se2(x)]) => Se2(b.se2_inverse(*x)),
            ("inverse", [So3(x)]) => So3(Builder::so3_transpose(*x)),
            ("inverse", [Se3(r, t)]) => {
                let (r, t) = b.se3_inverse((*r, *t));
                Se3(r, t)
            }
            ("between", [Se2(x), Se2(y)]) => Se2(b.se2_between(*x, *y)),
            ("between", [So3(x), So3(y)]) => So3(b.so3_mul(Builder::so3_transpose(*x), *y)),
            ("between", [Se3(r, t), Se3(q, u)]) => {
                let (r, t) = b.se3_between((*r, *t), (*q, *u));
                Se3(r, t)
            }
            ("act", [Se2(x), Vector(p)]) if p.len() == 2 => {
                Vector(b.se2_act(*x, [p[0], p[1]]).to_vec())
            }
            ("act", [So3(r), Vector(p)]) if p.len() == 3 => {
                Vector(b.so3_act(*r, [p[0], p[1], p[2]]).to_vec())
            }
            ("act", [Se3(r, t), Vector(p)]) if p.len() == 3 => {
                let moved = b.so3_act(*r, [p[0], p[1], p[2]]);
                Vector(b.add3(moved, *t).to_vec())
            }
            ("translation", [Se2(x)]) => Vector(vec![x[0], x[1]]),
            ("translation", [Se3(_, t)]) | ("translation", [Camera(_, t, _)]) => Vector(t.to_vec()),
            ("rotation", [Se3(r, _)]) | ("rotation", [Camera(r, _, _)]) => So3(*r),
            ("angle", [Se2(x)]) => Scalar(x[2]),
            ("intrinsics", [Camera(_, _, k)]) => Vector(k.to_vec()),
            ("exp_so3", [Vector(w)]) if w.len() == 3 => So3(b.so3_exp([w[0], w[1], w[2]])),
            ("exp_se2", [Vector(v)]) if v.len() == 3 => Se2(b.se2_exp([v[0], v[1], v[2]])),
            ("se2", [Scalar(x), Scalar(y), Scalar(t)]) => Se2([*x, *y, *t]),
            ("se3", [So3(r), Vector(t)]) if t.len() == 3 => Se3(*r, [t[0], t[1], t[2]]),
            _ => return None,
        })
    }
}
