//! Building a tape: scalar operations shared by value (the same operation on the same slots is
//! computed once, so `between(a, b)` used twice costs once), and the group operations of our
//! variable kinds written out over scalars.
//!
//! Conventions, the same as the built-in kinds: SE(2) is `(x, y, θ)` with `R(θ)`; rotations are
//! 3×3 matrices in nine row-major slots; SE(3) is `(R, t)` acting as `R p + t`.

use std::collections::HashMap;

use super::tape::{Op, Slot, Tape};

/// A value of the expression language, as the slots that hold it.
#[derive(Clone, Debug)]
pub(super) enum Typed {
    Scalar(Slot),
    Vector(Vec<Slot>),
    /// `[x, y, θ]`.
    Se2([Slot; 3]),
    /// Row-major rotation matrix.
    So3([Slot; 9]),
    /// Rotation and translation.
    Se3([Slot; 9], [Slot; 3]),
    /// A bundle-adjustment camera: rotation, translation, `[f, k1, k2]`.
    Camera([Slot; 9], [Slot; 3], [Slot; 3]),
}

impl Typed {
    /// The type's name in errors: `scalar`, `vector3`, `se2`, ….
    pub fn type_name(&self) -> String {
        match self {
            Typed::Scalar(_) => "scalar".into(),
            Typed::Vector(v) => format!("vector{}", v.len()),
            Typed::Se2(_) => "se2".into(),
            Typed::So3(_) => "so3".into(),
            Typed::Se3(..) => "se3".into(),
            Typed::Camera(..) => "snavely_camera".into(),
        }
    }
}

/// The tape under construction, with the node each slot came from (for error paths).
#[derive(Default)]
pub(super) struct Builder {
    ops: Vec<Op>,
    varying: Vec<bool>,
    /// Depends on neither a variable nor a parameter: the same at every evaluation.
    constant: Vec<bool>,
    shared: HashMap<Op, Slot>,
    /// The rotations `LogSo3` reads, each once (see `Op::LogSo3`).
    rotations: Vec<[Slot; 9]>,
    rotation_index: HashMap<[Slot; 9], u32>,
    /// Index into `paths` of the node that created each slot.
    origin: Vec<u32>,
    pub paths: Vec<String>,
}

impl Builder {
    /// Subsequent slots are reported as coming from the node at `path`.
    pub fn enter(&mut self, path: &str) -> u32 {
        self.paths.push(path.to_string());
        (self.paths.len() - 1) as u32
    }

    pub fn len(&self) -> usize {
        self.ops.len()
    }

    /// The tape, which slots are constant, and each slot's node.
    pub fn finish(self, outputs: Vec<Slot>) -> (Tape, Vec<bool>, Vec<u32>, Vec<String>) {
        (
            Tape::new(self.ops, self.varying, outputs, self.rotations),
            self.constant,
            self.origin,
            self.paths,
        )
    }

    /// Appends `op` (or finds it already computed) and returns its first slot.
    pub fn push(&mut self, op: Op) -> Slot {
        if let Some(&slot) = self.shared.get(&op) {
            return slot;
        }
        let args = op.arguments(&self.rotations);
        let varying = matches!(op, Op::Input(_)) || args.iter().any(|&a| self.varying[a as usize]);
        let constant = matches!(op, Op::Const(_))
            || (!args.is_empty() && args.iter().all(|&a| self.constant[a as usize]));
        let first = self.ops.len() as Slot;
        let origin = (self.paths.len().max(1) - 1) as u32;
        for k in 0..op.width() {
            self.ops.push(if k == 0 { op } else { Op::Filled });
            self.varying.push(varying);
            self.constant.push(constant);
            self.origin.push(origin);
        }
        self.shared.insert(op, first);
        first
    }

    pub fn constant_value(&mut self, value: f64) -> Slot {
        self.push(Op::Const(value.to_bits()))
    }
    pub fn add(&mut self, a: Slot, b: Slot) -> Slot {
        self.push(Op::Add(a, b))
    }
    pub fn sub(&mut self, a: Slot, b: Slot) -> Slot {
        self.push(Op::Sub(a, b))
    }
    pub fn mul(&mut self, a: Slot, b: Slot) -> Slot {
        self.push(Op::Mul(a, b))
    }
    pub fn neg(&mut self, a: Slot) -> Slot {
        self.push(Op::Neg(a))
    }
    pub fn sin(&mut self, a: Slot) -> Slot {
        self.push(Op::SinCos(a))
    }
    pub fn cos(&mut self, a: Slot) -> Slot {
        self.push(Op::SinCos(a)) + 1
    }

    /// `Σ a_k b_k`.
    pub fn dot(&mut self, a: &[Slot], b: &[Slot]) -> Slot {
        let mut sum = self.mul(a[0], b[0]);
        for k in 1..a.len() {
            let p = self.mul(a[k], b[k]);
            sum = self.add(sum, p);
        }
        sum
    }

    // SE(2)

    /// `R(θ) p`, or `R(θ)ᵀ p` when `transposed`.
    fn rotate2(&mut self, theta: Slot, p: [Slot; 2], transposed: bool) -> [Slot; 2] {
        let (c, s) = (self.cos(theta), self.sin(theta));
        let (cx, sy, sx, cy) = (
            self.mul(c, p[0]),
            self.mul(s, p[1]),
            self.mul(s, p[0]),
            self.mul(c, p[1]),
        );
        if transposed {
            [self.add(cx, sy), self.sub(cy, sx)]
        } else {
            [self.sub(cx, sy), self.add(sx, cy)]
        }
    }

    /// `a ∘ b = (t_a + R_a t_b, θ_a + θ_b)`.
    pub fn se2_compose(&mut self, a: [Slot; 3], b: [Slot; 3]) -> [Slot; 3] {
        let r = self.rotate2(a[2], [b[0], b[1]], false);
        [
            self.add(a[0], r[0]),
            self.add(a[1], r[1]),
            self.add(a[2], b[2]),
        ]
    }

    /// `a⁻¹ = (−R_aᵀ t_a, −θ_a)`.
    pub fn se2_inverse(&mut self, a: [Slot; 3]) -> [Slot; 3] {
        let r = self.rotate2(a[2], [a[0], a[1]], true);
        [self.neg(r[0]), self.neg(r[1]), self.neg(a[2])]
    }

    /// `a⁻¹ ∘ b = (R_aᵀ (t_b − t_a), θ_b − θ_a)`.
    pub fn se2_between(&mut self, a: [Slot; 3], b: [Slot; 3]) -> [Slot; 3] {
        let d = [self.sub(b[0], a[0]), self.sub(b[1], a[1])];
        let r = self.rotate2(a[2], d, true);
        [r[0], r[1], self.sub(b[2], a[2])]
    }

    /// `R p + t`.
    pub fn se2_act(&mut self, a: [Slot; 3], p: [Slot; 2]) -> [Slot; 2] {
        let r = self.rotate2(a[2], p, false);
        [self.add(a[0], r[0]), self.add(a[1], r[1])]
    }

    /// The Lie logarithm `[V⁻¹ t, θ]` with θ wrapped into (−π, π] and
    /// `V⁻¹ = [[h, θ/2], [−θ/2, h]]`, `h = (θ/2) cot(θ/2)`.
    pub fn se2_log(&mut self, a: [Slot; 3]) -> [Slot; 3] {
        let theta = self.push(Op::Wrap(a[2]));
        let h = self.push(Op::HalfCotHalf(theta));
        let half = self.constant_value(0.5);
        let half_theta = self.mul(half, theta);
        let (hx, ty) = (self.mul(h, a[0]), self.mul(half_theta, a[1]));
        let (hy, tx) = (self.mul(h, a[1]), self.mul(half_theta, a[0]));
        [self.add(hx, ty), self.sub(hy, tx), theta]
    }

    /// The Lie exponential of `[u, θ]`: `(V u, θ)`, `V = [[sinc θ, −cosc θ], [cosc θ, sinc θ]]`.
    pub fn se2_exp(&mut self, v: [Slot; 3]) -> [Slot; 3] {
        let (s, c) = (self.push(Op::Sinc(v[2])), self.push(Op::Cosc(v[2])));
        let (sx, cy, cx, sy) = (
            self.mul(s, v[0]),
            self.mul(c, v[1]),
            self.mul(c, v[0]),
            self.mul(s, v[1]),
        );
        [self.sub(sx, cy), self.add(cx, sy), v[2]]
    }

    // SO(3) and SE(3)

    /// `A B` for row-major 3×3 matrices.
    pub fn so3_mul(&mut self, a: [Slot; 9], b: [Slot; 9]) -> [Slot; 9] {
        let mut out = [0; 9];
        for r in 0..3 {
            for c in 0..3 {
                let row = [a[r * 3], a[r * 3 + 1], a[r * 3 + 2]];
                let col = [b[c], b[3 + c], b[6 + c]];
                out[r * 3 + c] = self.dot(&row, &col);
            }
        }
        out
    }

    pub fn so3_transpose(a: [Slot; 9]) -> [Slot; 9] {
        [a[0], a[3], a[6], a[1], a[4], a[7], a[2], a[5], a[8]]
    }

    /// `R p`.
    pub fn so3_act(&mut self, r: [Slot; 9], p: [Slot; 3]) -> [Slot; 3] {
        [
            self.dot(&r[0..3], &p),
            self.dot(&r[3..6], &p),
            self.dot(&r[6..9], &p),
        ]
    }

    pub fn so3_log(&mut self, r: [Slot; 9]) -> [Slot; 3] {
        let next = self.rotations.len() as u32;
        let k = *self.rotation_index.entry(r).or_insert(next);
        if k == next {
            self.rotations.push(r);
        }
        let first = self.push(Op::LogSo3(k));
        [first, first + 1, first + 2]
    }

    pub fn so3_exp(&mut self, w: [Slot; 3]) -> [Slot; 9] {
        let first = self.push(Op::ExpSo3(w));
        std::array::from_fn(|k| first + k as Slot)
    }

    pub fn add3(&mut self, a: [Slot; 3], b: [Slot; 3]) -> [Slot; 3] {
        [
            self.add(a[0], b[0]),
            self.add(a[1], b[1]),
            self.add(a[2], b[2]),
        ]
    }

    /// `(R_a R_b, R_a t_b + t_a)`.
    pub fn se3_compose(
        &mut self,
        a: ([Slot; 9], [Slot; 3]),
        b: ([Slot; 9], [Slot; 3]),
    ) -> ([Slot; 9], [Slot; 3]) {
        let r = self.so3_mul(a.0, b.0);
        let moved = self.so3_act(a.0, b.1);
        (r, self.add3(moved, a.1))
    }

    /// `(Rᵀ, −Rᵀ t)`.
    pub fn se3_inverse(&mut self, a: ([Slot; 9], [Slot; 3])) -> ([Slot; 9], [Slot; 3]) {
        let rt = Self::so3_transpose(a.0);
        let t = self.so3_act(rt, a.1);
        (rt, [self.neg(t[0]), self.neg(t[1]), self.neg(t[2])])
    }

    /// `a⁻¹ ∘ b = (R_aᵀ R_b, R_aᵀ (t_b − t_a))`.
    pub fn se3_between(
        &mut self,
        a: ([Slot; 9], [Slot; 3]),
        b: ([Slot; 9], [Slot; 3]),
    ) -> ([Slot; 9], [Slot; 3]) {
        let rt = Self::so3_transpose(a.0);
        let r = self.so3_mul(rt, b.0);
        let d = [
            self.sub(b.1[0], a.1[0]),
            self.sub(b.1[1], a.1[1]),
            self.sub(b.1[2], a.1[2]),
        ];
        (r, self.so3_act(rt, d))
    }
}
