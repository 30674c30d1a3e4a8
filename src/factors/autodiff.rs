//! Factors written in Rust with automatic derivatives: implement [`AutoResidual`] once,
//! generically over a [`Real`] scalar, and [`AutoFactor`] evaluates it with `f64` for the
//! residual and with [`Jet`]s (dual numbers with `N` derivative lanes, `N` the sum of the
//! variables' tangent dimensions) for the Jacobian — as Ceres' `AutoDiffCostFunction` or factrs'
//! residuals do. The library-side twin of `factors::expression` (user-defined factors over the
//! wire).
//!
//! The variables reach the residual already retracted by a tangent perturbation δ at δ = 0
//! ([`Lifted`]): `se2` as `(x + δx, y + δy, θ + δθ)`, `se3` as `(R Exp(ω), t + R v)` (first order:
//! `R (I + [ω]×)`), points additively. So the Jacobian is with respect to each variable's own
//! retraction, as for the built-in factors.
//!
//! ```
//! use factord::factors::autodiff::{AutoFactor, AutoResidual, Lifted, Real};
//!
//! /// Range from a pose to a point (both in the plane).
//! #[derive(Debug)]
//! struct Range(f64);
//!
//! impl AutoResidual<5> for Range {
//!     const NAME: &'static str = "my_range";
//!     const KINDS: &'static [&'static str] = &["se2", "point2"];
//!     const DIM: usize = 1;
//!     fn residual<T: Real>(&self, v: &[Lifted<T>], out: &mut [T]) {
//!         let (Lifted::Se2 { x, y, .. }, Lifted::Point2(p)) = (&v[0], &v[1]) else { unreachable!() };
//!         let (dx, dy) = (p[0] - *x, p[1] - *y);
//!         out[0] = (dx * dx + dy * dy).sqrt() - T::constant(self.0);
//!     }
//! }
//! let factor = AutoFactor::new(vec![0, 1], Range(5.0)).unwrap();
//! ```

use std::fmt::Debug;
use std::ops::{Add, Div, Mul, Neg, Sub};

use nalgebra::{Matrix3, Vector3};

use super::{expect_kind, EvaluationError, Factor};
use crate::geometry::{so3, Point2, Point3, Se2, Se3};
use crate::variables::{Key, Variable};

/// What a residual computes with: `f64`, or a [`Jet`] carrying derivatives.
pub trait Real:
    Copy
    + Debug
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
{
    fn constant(value: f64) -> Self;
    fn value(self) -> f64;
    fn sin(self) -> Self;
    fn cos(self) -> Self;
    fn sqrt(self) -> Self;
    fn exp(self) -> Self;
    fn ln(self) -> Self;
    /// `atan2(self, x)`.
    fn atan2(self, x: Self) -> Self;
    fn powf(self, exponent: f64) -> Self;
    /// The angle brought into (−π, π] (derivative 1).
    fn wrap(self) -> Self;
}

impl Real for f64 {
    fn constant(value: f64) -> Self {
        value
    }
    fn value(self) -> f64 {
        self
    }
    fn sin(self) -> Self {
        f64::sin(self)
    }
    fn cos(self) -> Self {
        f64::cos(self)
    }
    fn sqrt(self) -> Self {
        f64::sqrt(self)
    }
    fn exp(self) -> Self {
        f64::exp(self)
    }
    fn ln(self) -> Self {
        f64::ln(self)
    }
    fn atan2(self, x: Self) -> Self {
        f64::atan2(self, x)
    }
    fn powf(self, exponent: f64) -> Self {
        f64::powf(self, exponent)
    }
    fn wrap(self) -> Self {
        crate::geometry::wrap_angle(self)
    }
}

/// A value and its derivatives along `N` directions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Jet<const N: usize> {
    pub value: f64,
    pub derivative: [f64; N],
}

impl<const N: usize> Jet<N> {
    /// `value` with derivative 1 along `lane`.
    pub fn variable(value: f64, lane: usize) -> Self {
        let mut derivative = [0.0; N];
        derivative[lane] = 1.0;
        Self { value, derivative }
    }
    /// `f(value)` with `f'(value) = slope`: the chain rule.
    fn chain(self, value: f64, slope: f64) -> Self {
        Self {
            value,
            derivative: self.derivative.map(|d| d * slope),
        }
    }
}

impl<const N: usize> Add for Jet<N> {
    type Output = Self;
    fn add(self, o: Self) -> Self {
        Self {
            value: self.value + o.value,
            derivative: std::array::from_fn(|k| self.derivative[k] + o.derivative[k]),
        }
    }
}

impl<const N: usize> Sub for Jet<N> {
    type Output = Self;
    fn sub(self, o: Self) -> Self {
        Self {
            value: self.value - o.value,
            derivative: std::array::from_fn(|k| self.derivative[k] - o.derivative[k]),
        }
    }
}

impl<const N: usize> Mul for Jet<N> {
    type Output = Self;
    // The product rule adds.
    #[allow(clippy::suspicious_arithmetic_impl)]
    fn mul(self, o: Self) -> Self {
        Self {
            value: self.value * o.value,
            derivative: std::array::from_fn(|k| {
                self.derivative[k] * o.value + self.value * o.derivative[k]
            }),
        }
    }
}

impl<const N: usize> Div for Jet<N> {
    type Output = Self;
    // The quotient rule subtracts and multiplies.
    #[allow(clippy::suspicious_arithmetic_impl)]
    fn div(self, o: Self) -> Self {
        let inverse = 1.0 / o.value;
        let value = self.value * inverse;
        Self {
            value,
            derivative: std::array::from_fn(|k| {
                (self.derivative[k] - value * o.derivative[k]) * inverse
            }),
        }
    }
}

impl<const N: usize> Neg for Jet<N> {
    type Output = Self;
    fn neg(self) -> Self {
        self.chain(-self.value, -1.0)
    }
}

impl<const N: usize> Real for Jet<N> {
    fn constant(value: f64) -> Self {
        Self {
            value,
            derivative: [0.0; N],
        }
    }
    fn value(self) -> f64 {
        self.value
    }
    fn sin(self) -> Self {
        let (s, c) = self.value.sin_cos();
        self.chain(s, c)
    }
    fn cos(self) -> Self {
        let (s, c) = self.value.sin_cos();
        self.chain(c, -s)
    }
    fn sqrt(self) -> Self {
        let r = self.value.sqrt();
        self.chain(r, 0.5 / r)
    }
    fn exp(self) -> Self {
        let e = self.value.exp();
        self.chain(e, e)
    }
    fn ln(self) -> Self {
        self.chain(self.value.ln(), 1.0 / self.value)
    }
    fn atan2(self, x: Self) -> Self {
        let r2 = x.value * x.value + self.value * self.value;
        let (dy, dx) = (x.value / r2, -self.value / r2);
        Self {
            value: self.value.atan2(x.value),
            derivative: std::array::from_fn(|k| dy * self.derivative[k] + dx * x.derivative[k]),
        }
    }
    fn powf(self, exponent: f64) -> Self {
        self.chain(
            self.value.powf(exponent),
            exponent * self.value.powf(exponent - 1.0),
        )
    }
    fn wrap(self) -> Self {
        self.chain(crate::geometry::wrap_angle(self.value), 1.0)
    }
}

/// A variable as a residual sees it: its value moved by the tangent perturbation.
#[derive(Clone, Debug)]
pub enum Lifted<T> {
    Se2 {
        x: T,
        y: T,
        theta: T,
    },
    /// Rotation matrix (row-major rows) and translation.
    Se3 {
        rotation: [[T; 3]; 3],
        translation: [T; 3],
    },
    Point2([T; 2]),
    Point3([T; 3]),
}

/// A residual written once for any [`Real`]; `N` is the sum of its variables' tangent
/// dimensions (`se2` 3, `se3` 6, `point2` 2, `point3` 3).
pub trait AutoResidual<const N: usize>: Debug + Send + Sync + 'static {
    /// The factor's name in errors and summaries.
    const NAME: &'static str;
    /// The kinds of its variables, in key order.
    const KINDS: &'static [&'static str];
    /// The residual's dimension.
    const DIM: usize;
    fn residual<T: Real>(&self, variables: &[Lifted<T>], out: &mut [T]);
}

/// Why an [`AutoFactor`] cannot be made.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum AutoFactorError {
    #[error("{name}: {keys} keys for {kinds} variable kinds")]
    WrongKeys {
        name: &'static str,
        keys: usize,
        kinds: usize,
    },
    #[error("{name}: the variables' tangent dimensions add up to {tangent}, the residual declares {lanes} lanes")]
    WrongLanes {
        name: &'static str,
        tangent: usize,
        lanes: usize,
    },
    #[error("{name}: kind `{kind}` cannot be lifted (se2, se3, point2, point3)")]
    UnknownKind {
        name: &'static str,
        kind: &'static str,
    },
}

fn tangent_dim(kind: &str) -> Option<usize> {
    match kind {
        "se2" | "point3" => Some(3),
        "se3" => Some(6),
        "point2" => Some(2),
        _ => None,
    }
}

/// A [`Factor`] from an [`AutoResidual`].
#[derive(Debug)]
pub struct AutoFactor<R, const N: usize> {
    keys: Vec<Key>,
    pub residual: R,
}

impl<R: AutoResidual<N>, const N: usize> AutoFactor<R, N> {
    pub fn new(keys: Vec<Key>, residual: R) -> Result<Self, AutoFactorError> {
        let name = R::NAME;
        if keys.len() != R::KINDS.len() {
            let (keys, kinds) = (keys.len(), R::KINDS.len());
            return Err(AutoFactorError::WrongKeys { name, keys, kinds });
        }
        let mut tangent = 0;
        for &kind in R::KINDS {
            tangent += tangent_dim(kind).ok_or(AutoFactorError::UnknownKind { name, kind })?;
        }
        if tangent != N {
            return Err(AutoFactorError::WrongLanes {
                name,
                tangent,
                lanes: N,
            });
        }
        Ok(Self { keys, residual })
    }
}

/// The variables as `f64`s (no derivatives).
fn lift_values(
    kinds: &[&'static str],
    variables: &[&dyn Variable],
) -> Result<Vec<Lifted<f64>>, EvaluationError> {
    lift(kinds, variables, &mut 0, |v, _| v)
}

/// Each variable at δ = 0, each component a function of the lanes through `make(value, lane
/// seeds)`: `make` turns a value and its derivative along each lane into a scalar.
fn lift<T: Real>(
    kinds: &[&'static str],
    variables: &[&dyn Variable],
    lane: &mut usize,
    make: impl Fn(f64, &[(usize, f64)]) -> T,
) -> Result<Vec<Lifted<T>>, EvaluationError> {
    let mut lifted = Vec::with_capacity(kinds.len());
    for (position, &kind) in kinds.iter().enumerate() {
        let l = *lane;
        lifted.push(match kind {
            "se2" => {
                let p: &Se2 = expect_kind(variables, position, kind)?;
                Lifted::Se2 {
                    x: make(p.x, &[(l, 1.0)]),
                    y: make(p.y, &[(l + 1, 1.0)]),
                    theta: make(p.theta, &[(l + 2, 1.0)]),
                }
            }
            "point2" => {
                let p: &Point2 = expect_kind(variables, position, kind)?;
                Lifted::Point2(std::array::from_fn(|k| make(p.0[k], &[(l + k, 1.0)])))
            }
            "point3" => {
                let p: &Point3 = expect_kind(variables, position, kind)?;
                Lifted::Point3(std::array::from_fn(|k| make(p.0[k], &[(l + k, 1.0)])))
            }
            "se3" => {
                // (R Exp(ω), t + R v): ∂R/∂ω_m = R [e_m]×, ∂t/∂v = R.
                let p: &Se3 = expect_kind(variables, position, kind)?;
                let r: Matrix3<f64> = p.rotation.to_rotation_matrix().into_inner();
                let d: [Matrix3<f64>; 3] =
                    std::array::from_fn(|m| r * so3::hat(&Vector3::ith(m, 1.0)));
                Lifted::Se3 {
                    rotation: std::array::from_fn(|i| {
                        std::array::from_fn(|j| {
                            let seeds: [(usize, f64); 3] =
                                std::array::from_fn(|m| (l + 3 + m, d[m][(i, j)]));
                            make(r[(i, j)], &seeds)
                        })
                    }),
                    translation: std::array::from_fn(|i| {
                        let seeds: [(usize, f64); 3] = std::array::from_fn(|m| (l + m, r[(i, m)]));
                        make(p.translation[i], &seeds)
                    }),
                }
            }
            _ => unreachable!("kinds are checked when the factor is made"),
        });
        *lane += tangent_dim(kind).expect("checked");
    }
    Ok(lifted)
}

impl<R: AutoResidual<N>, const N: usize> Factor for AutoFactor<R, N> {
    fn name(&self) -> &str {
        R::NAME
    }
    fn keys(&self) -> &[Key] {
        &self.keys
    }
    fn residual_dim(&self) -> usize {
        R::DIM
    }
    fn variable_kinds(&self) -> &[&'static str] {
        R::KINDS
    }
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let Some(jacobian) = jacobian else {
            self.residual
                .residual(&lift_values(R::KINDS, variables)?, error);
            return Ok(());
        };
        let lifted = lift(R::KINDS, variables, &mut 0, |value, seeds| {
            let mut jet = Jet::<N>::constant(value);
            for &(lane, d) in seeds {
                jet.derivative[lane] = d;
            }
            jet
        })?;
        let mut out = vec![Jet::<N>::constant(0.0); R::DIM];
        self.residual.residual(&lifted, &mut out);
        for (row, jet) in out.iter().enumerate() {
            error[row] = jet.value;
            jacobian[row * N..(row + 1) * N].copy_from_slice(&jet.derivative);
        }
        Ok(())
    }
    fn as_any(&self) -> &dyn std::any::Any {
        self
    }
}

/// The built-in `between_se2` written as an [`AutoResidual`]: an example, and what
/// `benches/expression` measures automatic differentiation with.
/// Residual `[R_ijᵀ (R_iᵀ (t_j − t_i) − t_ij); wrap(θ_j − θ_i − θ_ij)]`, measurement `Z = (t_ij, θ_ij)`.
#[derive(Debug)]
pub struct AutoBetweenSe2(pub Se2);

impl AutoResidual<6> for AutoBetweenSe2 {
    const NAME: &'static str = "rust_between_se2";
    const KINDS: &'static [&'static str] = &["se2", "se2"];
    const DIM: usize = 3;
    fn residual<T: Real>(&self, v: &[Lifted<T>], out: &mut [T]) {
        let (
            Lifted::Se2 {
                x: xi,
                y: yi,
                theta: ti,
            },
            Lifted::Se2 {
                x: xj,
                y: yj,
                theta: tj,
            },
        ) = (&v[0], &v[1])
        else {
            unreachable!("kinds are declared")
        };
        let (c, s) = (ti.cos(), ti.sin());
        let (dx, dy) = (*xj - *xi, *yj - *yi);
        let (ax, ay) = (c * dx + s * dy, c * dy - s * dx);
        let z = self.0;
        let (cz, sz) = (T::constant(z.theta.cos()), T::constant(z.theta.sin()));
        let (ux, uy) = (ax - T::constant(z.x), ay - T::constant(z.y));
        out[0] = cz * ux + sz * uy;
        out[1] = cz * uy - sz * ux;
        out[2] = (*tj - *ti - T::constant(z.theta)).wrap();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::testing::{assert_jacobians_match, Rng};
    use crate::factors::BetweenSe2;

    /// A landmark's position in a pose's frame, `Rᵀ (p − t)`, and its distance.
    #[derive(Debug)]
    struct Seen;

    impl AutoResidual<9> for Seen {
        const NAME: &'static str = "seen";
        const KINDS: &'static [&'static str] = &["se3", "point3"];
        const DIM: usize = 4;
        fn residual<T: Real>(&self, v: &[Lifted<T>], out: &mut [T]) {
            let (
                Lifted::Se3 {
                    rotation: r,
                    translation: t,
                },
                Lifted::Point3(p),
            ) = (&v[0], &v[1])
            else {
                unreachable!("kinds are declared")
            };
            let d: [T; 3] = std::array::from_fn(|k| p[k] - t[k]);
            for i in 0..3 {
                out[i] = r[0][i] * d[0] + r[1][i] * d[1] + r[2][i] * d[2];
            }
            out[3] = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        }
    }

    #[test]
    fn a_rust_between_se2_equals_the_built_in_factor() {
        let mut rng = Rng::new(29);
        for _ in 0..200 {
            let z = rng.se2();
            let auto = AutoFactor::new(vec![0, 1], AutoBetweenSe2(z)).unwrap();
            let built_in = BetweenSe2::new(0, 1, z);
            let vars: Vec<Box<dyn Variable>> = vec![Box::new(rng.se2()), Box::new(rng.se2())];
            let refs: Vec<&dyn Variable> = vars.iter().map(|v| v.as_ref()).collect();
            let (mut e0, mut e1, mut j0, mut j1) = ([0.0; 3], [0.0; 3], [0.0; 18], [0.0; 18]);
            built_in.evaluate(&refs, &mut e0, Some(&mut j0)).unwrap();
            auto.evaluate(&refs, &mut e1, Some(&mut j1)).unwrap();
            for (a, b) in e0.iter().chain(&j0).zip(e1.iter().chain(&j1)) {
                assert!((a - b).abs() < 1e-12, "{e0:?} {j0:?}\nvs\n{e1:?} {j1:?}");
            }
            let mut e2 = [0.0; 3];
            auto.evaluate(&refs, &mut e2, None).unwrap();
            assert_eq!(e1, e2);
        }
    }

    #[test]
    fn se3_and_point3_lift_through_their_retractions() {
        let mut rng = Rng::new(31);
        for _ in 0..200 {
            let auto = AutoFactor::new(vec![0, 1], Seen).unwrap();
            let vars: Vec<Box<dyn Variable>> =
                vec![Box::new(rng.se3()), Box::new(Point3(rng.vector3(3.0)))];
            assert_jacobians_match(&auto, &vars);
        }
    }

    #[test]
    fn a_residual_whose_lanes_do_not_add_up_is_refused() {
        #[derive(Debug)]
        struct Wrong;
        impl AutoResidual<4> for Wrong {
            const NAME: &'static str = "wrong";
            const KINDS: &'static [&'static str] = &["se2", "point2"];
            const DIM: usize = 1;
            fn residual<T: Real>(&self, _: &[Lifted<T>], out: &mut [T]) {
                out[0] = T::constant(0.0);
            }
        }
        assert_eq!(
            AutoFactor::new(vec![0, 1], Wrong).unwrap_err(),
            AutoFactorError::WrongLanes {
                name: "wrong",
                tangent: 5,
                lanes: 4
            }
        );
        assert!(matches!(
            AutoFactor::new(vec![0], Wrong),
            Err(AutoFactorError::WrongKeys { .. })
        ));
    }
}
