//! The compiled form of an expression: a straight-line tape of scalar operations, evaluated in
//! forward mode with dual numbers of `lanes` components (one per tangent direction of the
//! factor's variables).
//!
//! Every slot holds a value and, when a Jacobian is asked for, its gradient with respect to the
//! tangent perturbation δ of all variables at δ = 0. An operation `c = f(a, b)` writes
//! `c = f(a, b)` and `∇c = ∂f/∂a ∇a + ∂f/∂b ∇b`: each scalar operation only knows its two local
//! partial derivatives, so adding one is one match arm. Slots that depend on no variable
//! (constants, parameters, and what is computed from them only) are marked at compile time and
//! their gradient is never touched: it is zero by construction.
//!
//! Two operations produce several slots at once because their scalar forms are singular where
//! they are used most (the rotation logarithm at the identity): `LogSo3` and `ExpSo3` are
//! evaluated in closed form with their own Jacobians (`J_r⁻¹`, `J_r`).

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};

use crate::geometry::so3;

pub(super) type Slot = u32;

/// One tape entry. Single-output operations write their own slot; `LogSo3` writes its slot and
/// the two after it, `ExpSo3` its slot and the eight after it (those hold `Filled`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub(super) enum Op {
    /// Component `k` of the variables' seeded inputs.
    Input(u32),
    /// Number `k` of the factor's lowered measurement.
    Param(u32),
    /// A constant, by its bits (so operations can be hashed for sharing).
    Const(u64),
    Add(Slot, Slot),
    Sub(Slot, Slot),
    Mul(Slot, Slot),
    Div(Slot, Slot),
    Neg(Slot),
    Tan(Slot),
    Asin(Slot),
    Acos(Slot),
    Atan(Slot),
    Atan2(Slot, Slot),
    Sqrt(Slot),
    Exp(Slot),
    Ln(Slot),
    Abs(Slot),
    Pow(Slot, Slot),
    /// The angle brought into (−π, π]; derivative 1.
    Wrap(Slot),
    /// sin x / x, exact near 0.
    Sinc(Slot),
    /// (1 − cos x) / x, exact near 0.
    Cosc(Slot),
    /// (x/2) cot(x/2), exact near 0 (the SE(2) logarithm's V⁻¹).
    HalfCotHalf(Slot),
    /// sin and cos of one slot: two outputs (an angle's are nearly always both needed, and
    /// one `sin_cos` costs what one of them does).
    SinCos(Slot),
    /// Log of the rotation in the nine row-major slots `Tape::rotations[k]`: three outputs.
    /// (Those nine slots in line made every operation 40 bytes instead of 16.)
    LogSo3(u32),
    /// Exp of the vector in three slots: nine outputs (row-major rotation matrix).
    ExpSo3([Slot; 3]),
    /// Written by the multi-output operation before it.
    Filled,
}

impl Op {
    /// How many slots it writes.
    pub fn width(&self) -> usize {
        match self {
            Op::SinCos(_) => 2,
            Op::LogSo3(_) => 3,
            Op::ExpSo3(_) => 9,
            _ => 1,
        }
    }

    /// The operands of a single-output operation, in the order of its partial derivatives.
    fn scalar_operands(&self) -> [Option<Slot>; 2] {
        use Op::*;
        match *self {
            Add(a, b) | Sub(a, b) | Mul(a, b) | Div(a, b) | Atan2(a, b) | Pow(a, b) => {
                [Some(a), Some(b)]
            }
            Neg(a) | Tan(a) | Asin(a) | Acos(a) | Atan(a) | Sqrt(a) | Exp(a) | Ln(a) | Abs(a)
            | Wrap(a) | Sinc(a) | Cosc(a) | HalfCotHalf(a) => [Some(a), None],
            Input(_) | Param(_) | Const(_) | Filled | SinCos(_) | LogSo3(_) | ExpSo3(_) => {
                [None, None]
            }
        }
    }

    /// The slots it reads (`rotations`: the tape's, which `LogSo3` points into).
    pub fn arguments(&self, rotations: &[[Slot; 9]]) -> Vec<Slot> {
        use Op::*;
        match *self {
            Input(_) | Param(_) | Const(_) | Filled => vec![],
            Add(a, b) | Sub(a, b) | Mul(a, b) | Div(a, b) | Atan2(a, b) | Pow(a, b) => vec![a, b],
            Neg(a) | Tan(a) | Asin(a) | Acos(a) | Atan(a) | Sqrt(a) | Exp(a) | Ln(a) | Abs(a)
            | Wrap(a) | Sinc(a) | Cosc(a) | HalfCotHalf(a) | SinCos(a) => vec![a],
            LogSo3(k) => rotations[k as usize].to_vec(),
            ExpSo3(w) => w.to_vec(),
        }
    }
}

/// Below this magnitude the closed forms of `Sinc`, `Cosc` and `HalfCotHalf` give way to series.
const SMALL: f64 = 1e-4;

/// Value and the two local partial derivatives of a single-output operation (inlined, so a
/// value-only evaluation does not compute the partials).
#[inline(always)]
fn scalar(op: Op, v: &[f64]) -> (f64, f64, f64) {
    use Op::*;
    let at = |s: Slot| v[s as usize];
    match op {
        Const(bits) => (f64::from_bits(bits), 0.0, 0.0),
        Add(a, b) => (at(a) + at(b), 1.0, 1.0),
        Sub(a, b) => (at(a) - at(b), 1.0, -1.0),
        Mul(a, b) => (at(a) * at(b), at(b), at(a)),
        Div(a, b) => {
            let (x, y) = (at(a), at(b));
            (x / y, 1.0 / y, -x / (y * y))
        }
        Neg(a) => (-at(a), -1.0, 0.0),
        Tan(a) => {
            let t = at(a).tan();
            (t, 1.0 + t * t, 0.0)
        }
        Asin(a) => (at(a).asin(), 1.0 / (1.0 - at(a) * at(a)).sqrt(), 0.0),
        Acos(a) => (at(a).acos(), -1.0 / (1.0 - at(a) * at(a)).sqrt(), 0.0),
        Atan(a) => (at(a).atan(), 1.0 / (1.0 + at(a) * at(a)), 0.0),
        Atan2(a, b) => {
            let (y, x) = (at(a), at(b));
            let r2 = x * x + y * y;
            (y.atan2(x), x / r2, -y / r2)
        }
        Sqrt(a) => {
            let s = at(a).sqrt();
            (s, 0.5 / s, 0.0)
        }
        Exp(a) => {
            let e = at(a).exp();
            (e, e, 0.0)
        }
        Ln(a) => (at(a).ln(), 1.0 / at(a), 0.0),
        Abs(a) => (at(a).abs(), if at(a) < 0.0 { -1.0 } else { 1.0 }, 0.0),
        Pow(a, b) => {
            let (x, y) = (at(a), at(b));
            let p = x.powf(y);
            // ∂/∂y = p ln x is only needed (and only defined) when the exponent varies; the
            // caller skips partials of arguments that do not vary.
            (p, y * x.powf(y - 1.0), p * x.ln())
        }
        Wrap(a) => (crate::geometry::wrap_angle(at(a)), 1.0, 0.0),
        Sinc(a) => {
            let x = at(a);
            if x.abs() < SMALL {
                (1.0 - x * x / 6.0, -x / 3.0 + x * x * x / 30.0, 0.0)
            } else {
                let (s, c) = x.sin_cos();
                (s / x, (x * c - s) / (x * x), 0.0)
            }
        }
        Cosc(a) => {
            let x = at(a);
            if x.abs() < SMALL {
                (x / 2.0 - x * x * x / 24.0, 0.5 - x * x / 8.0, 0.0)
            } else {
                let (s, c) = x.sin_cos();
                ((1.0 - c) / x, (x * s - (1.0 - c)) / (x * x), 0.0)
            }
        }
        HalfCotHalf(a) => {
            let x = at(a);
            if x.abs() < SMALL {
                let x2 = x * x;
                (
                    1.0 - x2 / 12.0 - x2 * x2 / 720.0,
                    -x / 6.0 - x2 * x / 180.0,
                    0.0,
                )
            } else {
                let (s, c) = (0.5 * x).sin_cos();
                (0.5 * x * c / s, 0.5 * c / s - 0.25 * x / (s * s), 0.0)
            }
        }
        Input(_) | Param(_) | Filled | SinCos(_) | LogSo3(_) | ExpSo3(_) => {
            unreachable!("not a scalar operation: {op:?}")
        }
    }
}

/// A compiled residual: operations in evaluation order, which slots vary with δ, and which
/// slots form the residual.
///
/// What does not depend on the variables (a measurement's sine and cosine, a parameter's
/// inverse) is computed once per factor, when it is built ([`Tape::fixed_part`]): an evaluation
/// runs only the operations that vary, reading the fixed slots they need (the *frontier*) from
/// the factor.
#[derive(Clone, Debug, Default)]
pub(super) struct Tape {
    pub ops: Vec<Op>,
    /// Whether slot `i` depends on a variable (its gradient is meaningful).
    pub varying: Vec<bool>,
    pub outputs: Vec<Slot>,
    /// The rotations `LogSo3` operations read, by index.
    rotations: Vec<[Slot; 9]>,
    /// Indices of the operations that vary, in order.
    varying_ops: Vec<Slot>,
    /// Fixed slots read by a varying operation or part of the residual.
    frontier: Vec<Slot>,
    /// For each of `varying_ops`, its operands that vary (whose gradients it combines).
    varying_operands: Vec<[Option<Slot>; 2]>,
}

/// The variables' values as tape inputs, and each input's gradient row (`lanes` long).
pub(super) struct Seeds {
    pub values: Vec<f64>,
    pub gradients: Vec<f64>,
}

/// Scratch for one evaluation; kept per thread so a solve evaluates without allocating.
#[derive(Default)]
pub(super) struct Scratch {
    values: Vec<f64>,
    gradients: Vec<f64>,
}

impl Tape {
    pub fn new(
        mut ops: Vec<Op>,
        mut varying: Vec<bool>,
        mut outputs: Vec<Slot>,
        mut rotations: Vec<[Slot; 9]>,
    ) -> Self {
        // Built by pushing: up to twice the length in capacity, held as long as the type.
        ops.shrink_to_fit();
        varying.shrink_to_fit();
        outputs.shrink_to_fit();
        rotations.shrink_to_fit();
        let varying_ops: Vec<Slot> = (0..ops.len())
            .filter(|&i| varying[i] && ops[i] != Op::Filled)
            .map(|i| i as Slot)
            .collect();
        let mut frontier: Vec<Slot> = varying_ops
            .iter()
            .flat_map(|&i| ops[i as usize].arguments(&rotations))
            .chain(outputs.iter().copied())
            .filter(|&s| !varying[s as usize])
            .collect();
        frontier.sort_unstable();
        frontier.dedup();
        frontier.shrink_to_fit();
        let varying_operands = varying_ops
            .iter()
            .map(|&i| {
                ops[i as usize]
                    .scalar_operands()
                    .map(|a| a.filter(|&a| varying[a as usize]))
            })
            .collect();
        Self {
            ops,
            varying,
            outputs,
            rotations,
            varying_ops,
            frontier,
            varying_operands,
        }
    }

    /// Bytes its vectors hold.
    pub fn heap_bytes(&self) -> usize {
        use std::mem::size_of;
        self.ops.capacity() * size_of::<Op>()
            + self.varying.capacity()
            + (self.outputs.capacity() + self.varying_ops.capacity() + self.frontier.capacity())
                * size_of::<Slot>()
            + self.varying_operands.capacity() * size_of::<[Option<Slot>; 2]>()
            + self.rotations.capacity() * size_of::<[Slot; 9]>()
    }

    pub fn varying_operations(&self) -> usize {
        self.varying_ops.len()
    }

    /// Computes every fixed slot from the factor's `params` into `scratch` and returns the
    /// frontier's values, which [`Tape::evaluate`] takes.
    pub fn fixed_part(&self, params: &[f64], scratch: &mut Scratch) -> Vec<f64> {
        let n = self.ops.len();
        scratch.values.resize(n, 0.0);
        let values = &mut scratch.values;
        for i in (0..n).filter(|&i| !self.varying[i]) {
            match self.ops[i] {
                Op::Param(k) => values[i] = params[k as usize],
                Op::Filled => {}
                Op::SinCos(a) => (values[i], values[i + 1]) = values[a as usize].sin_cos(),
                Op::LogSo3(k) => log_so3(i, self.rotations[k as usize], values, &mut [], 0, None),
                Op::ExpSo3(w) => exp_so3(i, w, values, &mut [], 0, None),
                op => values[i] = scalar(op, values).0,
            }
        }
        self.frontier.iter().map(|&s| values[s as usize]).collect()
    }

    /// Evaluates into `error` and, when asked, the Jacobian (row-major, residual × lanes),
    /// with `fixed` the factor's frontier values from [`Tape::fixed_part`].
    pub fn evaluate(
        &self,
        seeds: &Seeds,
        fixed: &[f64],
        lanes: usize,
        scratch: &mut Scratch,
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) {
        // The common widths get their own copy of the loop with `lanes` a constant, so the
        // per-operation gradient updates are unrolled (measured: 1.4x faster solves on intel
        // than one loop over a variable width).
        match lanes {
            3 => self.run(seeds, fixed, 3, scratch, error, jacobian),
            6 => self.run(seeds, fixed, 6, scratch, error, jacobian),
            9 => self.run(seeds, fixed, 9, scratch, error, jacobian),
            12 => self.run(seeds, fixed, 12, scratch, error, jacobian),
            15 => self.run(seeds, fixed, 15, scratch, error, jacobian),
            _ => self.run(seeds, fixed, lanes, scratch, error, jacobian),
        }
    }

    #[inline(always)]
    fn run(
        &self,
        seeds: &Seeds,
        fixed: &[f64],
        lanes: usize,
        scratch: &mut Scratch,
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) {
        let n = self.ops.len();
        let with_gradient = jacobian.is_some();
        scratch.values.resize(n, 0.0);
        if with_gradient {
            scratch.gradients.resize(n * lanes, 0.0);
        }
        let values = &mut scratch.values;
        let gradients = &mut scratch.gradients;
        for (&s, &v) in self.frontier.iter().zip(fixed) {
            values[s as usize] = v;
        }
        for (&i, &[a, b]) in self.varying_ops.iter().zip(&self.varying_operands) {
            let i = i as usize;
            let op = self.ops[i];
            match op {
                Op::Input(k) => {
                    values[i] = seeds.values[k as usize];
                    if with_gradient {
                        let k = k as usize;
                        gradients[i * lanes..(i + 1) * lanes]
                            .copy_from_slice(&seeds.gradients[k * lanes..(k + 1) * lanes]);
                    }
                }
                Op::Param(_) | Op::Const(_) | Op::Filled => unreachable!("fixed, not varying"),
                Op::SinCos(a) => {
                    let (sin, cos) = values[a as usize].sin_cos();
                    (values[i], values[i + 1]) = (sin, cos);
                    if with_gradient {
                        // The operand varies, or this would not.
                        let (head, tail) = gradients.split_at_mut(i * lanes);
                        let g = &head[a as usize * lanes..(a as usize + 1) * lanes];
                        for k in 0..lanes {
                            tail[k] = cos * g[k];
                            tail[lanes + k] = -sin * g[k];
                        }
                    }
                }
                Op::LogSo3(k) => {
                    let grad = with_gradient.then_some(&self.varying[..]);
                    log_so3(
                        i,
                        self.rotations[k as usize],
                        values,
                        gradients,
                        lanes,
                        grad,
                    )
                }
                Op::ExpSo3(w) => {
                    let grad = with_gradient.then_some(&self.varying[..]);
                    exp_so3(i, w, values, gradients, lanes, grad)
                }
                _ => {
                    let (value, da, db) = scalar(op, values);
                    values[i] = value;
                    if with_gradient {
                        let (head, tail) = gradients.split_at_mut(i * lanes);
                        let out = &mut tail[..lanes];
                        let gradient_of = |arg: Option<Slot>| {
                            arg.map(|a| &head[a as usize * lanes..(a as usize + 1) * lanes])
                        };
                        match (gradient_of(a), gradient_of(b)) {
                            (Some(ga), Some(gb)) => {
                                for k in 0..lanes {
                                    out[k] = da * ga[k] + db * gb[k];
                                }
                            }
                            (Some(g), None) => (0..lanes).for_each(|k| out[k] = da * g[k]),
                            (None, Some(g)) => (0..lanes).for_each(|k| out[k] = db * g[k]),
                            (None, None) => unreachable!("a varying slot has a varying operand"),
                        }
                    }
                }
            }
        }
        for (e, &s) in error.iter_mut().zip(&self.outputs) {
            *e = values[s as usize];
        }
        if let Some(j) = jacobian {
            for (row, &s) in self.outputs.iter().enumerate() {
                let out = &mut j[row * lanes..(row + 1) * lanes];
                if self.varying[s as usize] {
                    out.copy_from_slice(&gradients[s as usize * lanes..(s as usize + 1) * lanes]);
                } else {
                    out.fill(0.0);
                }
            }
        }
    }

    /// The first slot, in evaluation order, of those an evaluation computes or reads (the
    /// varying ones and the frontier), whose last value is not finite.
    pub fn first_non_finite(&self, scratch: &Scratch) -> Option<Slot> {
        let mut read: Vec<Slot> = self
            .frontier
            .iter()
            .chain(&self.varying_ops)
            .copied()
            .collect();
        read.sort_unstable();
        read.into_iter()
            .find(|&s| !scratch.values[s as usize].is_finite())
    }
}

impl Scratch {
    /// The value of `slot` in the last evaluation.
    pub fn value(&self, slot: Slot) -> f64 {
        self.values[slot as usize]
    }
}

fn matrix_at(slots: &[Slot; 9], values: &[f64]) -> Matrix3<f64> {
    Matrix3::from_fn(|r, c| values[slots[r * 3 + c] as usize])
}

/// Lane `lane` of the gradient of `slot`: zero for a slot that does not vary (its gradient row
/// holds no meaningful numbers).
fn lane_of(slot: Slot, gradients: &[f64], varying: &[bool], lanes: usize, lane: usize) -> f64 {
    if varying[slot as usize] {
        gradients[slot as usize * lanes + lane]
    } else {
        0.0
    }
}

/// ω = Log(R), dω = J_r⁻¹(ω) vee(Rᵀ dR): Rᵀ dR is skew for any rotation-valued path, and its
/// skew part is taken so rounding in dR does not leak in.
fn log_so3(
    out: usize,
    r: [Slot; 9],
    values: &mut [f64],
    gradients: &mut [f64],
    lanes: usize,
    varying: Option<&[bool]>,
) {
    let m = matrix_at(&r, values);
    let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(m));
    let w = so3::log(&q);
    values[out..out + 3].copy_from_slice(w.as_slice());
    let Some(varying) = varying else { return };
    let j = so3::right_jacobian_inv(&w);
    let (head, tail) = gradients.split_at_mut(out * lanes);
    for lane in 0..lanes {
        let dm = Matrix3::from_fn(|row, col| lane_of(r[row * 3 + col], head, varying, lanes, lane));
        let a = m.transpose() * dm;
        let v = 0.5
            * Vector3::new(
                a[(2, 1)] - a[(1, 2)],
                a[(0, 2)] - a[(2, 0)],
                a[(1, 0)] - a[(0, 1)],
            );
        let d = j * v;
        for k in 0..3 {
            tail[k * lanes + lane] = d[k];
        }
    }
}

/// R = Exp(ω), dR = R [J_r(ω) dω]×.
fn exp_so3(
    out: usize,
    w: [Slot; 3],
    values: &mut [f64],
    gradients: &mut [f64],
    lanes: usize,
    varying: Option<&[bool]>,
) {
    let omega = Vector3::new(
        values[w[0] as usize],
        values[w[1] as usize],
        values[w[2] as usize],
    );
    let m = so3::exp(&omega).to_rotation_matrix().into_inner();
    for k in 0..9 {
        values[out + k] = m[(k / 3, k % 3)];
    }
    let Some(varying) = varying else { return };
    let j = so3::right_jacobian(&omega);
    let (head, tail) = gradients.split_at_mut(out * lanes);
    for lane in 0..lanes {
        let dw = Vector3::from_fn(|k, _| lane_of(w[k], head, varying, lanes, lane));
        let dm = m * so3::hat(&(j * dw));
        for k in 0..9 {
            tail[k * lanes + lane] = dm[(k / 3, k % 3)];
        }
    }
}
