//! The shared Jacobian check: every factor's analytic Jacobians against central differences taken
//! through each variable's own retraction, plus a small deterministic generator of random poses
//! whose angles include the ±π neighbourhood.

use std::f64::consts::PI;

use nalgebra::Vector3;

use super::Factor;
use crate::geometry::{so3, wrap_angle, NavState, Se2, Se3};
use crate::variables::Variable;

/// SplitMix64: deterministic, dependency-free randomness for tests and synthetic fixtures.
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    /// Uniform in [-1, 1).
    pub fn symmetric(&mut self) -> f64 {
        2.0 * self.uniform() - 1.0
    }
    /// Uniform in 0..n (n > 0).
    pub fn below(&mut self, n: usize) -> usize {
        (self.next_u64() % n as u64) as usize
    }
    /// Standard normal (Box-Muller).
    pub fn normal(&mut self) -> f64 {
        let u = self.uniform().max(1e-300);
        let v = self.uniform();
        (-2.0 * u.ln()).sqrt() * (2.0 * PI * v).cos()
    }
    /// An angle: one time in four within 1e-3 of ±π, otherwise uniform.
    pub fn angle(&mut self) -> f64 {
        if self.next_u64().is_multiple_of(4) {
            let sign = if self.next_u64().is_multiple_of(2) {
                1.0
            } else {
                -1.0
            };
            sign * (PI - 1e-3 * self.uniform())
        } else {
            (2.0 * self.uniform() - 1.0) * PI
        }
    }
    pub fn se2(&mut self) -> Se2 {
        Se2::new(4.0 * self.normal(), 4.0 * self.normal(), self.angle())
    }
    pub fn vector3(&mut self, scale: f64) -> Vector3<f64> {
        Vector3::new(self.normal(), self.normal(), self.normal()) * scale
    }
    /// A random navigation state: any pose, velocity of a few m/s, small biases.
    pub fn nav_state(&mut self) -> NavState {
        let pose = self.se3();
        NavState {
            position: pose.translation,
            rotation: pose.rotation,
            velocity: self.vector3(2.0),
            accel_bias: self.vector3(0.1),
            gyro_bias: self.vector3(0.01),
        }
    }
    pub fn se3(&mut self) -> Se3 {
        let axis = Vector3::new(self.normal(), self.normal(), self.normal()).normalize();
        Se3::new(
            so3::exp(&(axis * self.angle().abs())),
            Vector3::new(self.normal(), self.normal(), self.normal()) * 4.0,
        )
    }
}

/// Central-difference Jacobian of the factor's error, row-major like [`Factor::evaluate`].
///
/// Error differences are wrapped into (−π, π]: two errors a step apart only differ by ≈2π when an
/// angle component crossed the branch cut, and that jump is not part of the derivative.
pub fn numeric_jacobian(
    factor: &dyn Factor,
    variables: &[Box<dyn Variable>],
    step: f64,
) -> Vec<f64> {
    let d = factor.residual_dim();
    let cols: usize = variables.iter().map(|v| v.tangent_dim()).sum();
    let mut out = vec![0.0; d * cols];
    let mut col0 = 0;
    for (k, var) in variables.iter().enumerate() {
        for c in 0..var.tangent_dim() {
            let eval = |sign: f64| {
                let mut perturbed: Vec<Box<dyn Variable>> =
                    variables.iter().map(|v| v.clone_box()).collect();
                let mut delta = vec![0.0; var.tangent_dim()];
                delta[c] = sign * step;
                perturbed[k].retract(&delta);
                let refs: Vec<&dyn Variable> = perturbed.iter().map(|v| v.as_ref()).collect();
                let mut e = vec![0.0; d];
                factor
                    .evaluate(&refs, &mut e, None)
                    .expect("numeric jacobian: evaluation failed");
                e
            };
            let plus = eval(1.0);
            let minus = eval(-1.0);
            for r in 0..d {
                let mut diff = plus[r] - minus[r];
                if diff.abs() > PI {
                    diff = wrap_angle(diff);
                }
                out[r * cols + col0 + c] = diff / (2.0 * step);
            }
        }
        col0 += var.tangent_dim();
    }
    out
}

/// Panics with a readable report when analytic and numeric Jacobians disagree, or when a value
/// the factor predicts for one of its variables does not zero its error.
pub fn assert_jacobians_match(factor: &dyn Factor, variables: &[Box<dyn Variable>]) {
    assert_predictions_zero_error(factor, variables);
    let d = factor.residual_dim();
    let cols: usize = variables.iter().map(|v| v.tangent_dim()).sum();
    let refs: Vec<&dyn Variable> = variables.iter().map(|v| v.as_ref()).collect();
    let mut e = vec![0.0; d];
    let mut analytic = vec![0.0; d * cols];
    factor
        .evaluate(&refs, &mut e, Some(&mut analytic))
        .expect("evaluation failed");
    let numeric = numeric_jacobian(factor, variables, 1e-6);
    for r in 0..d {
        for c in 0..cols {
            let (a, n) = (analytic[r * cols + c], numeric[r * cols + c]);
            assert!(
                (a - n).abs() <= 1e-5 * (1.0 + n.abs()),
                "{}: ∂e[{r}]/∂δ[{c}] analytic {a} vs numeric {n}\nvariables: {variables:?}\nerror: {e:?}",
                factor.name()
            );
        }
    }
}

fn assert_predictions_zero_error(factor: &dyn Factor, variables: &[Box<dyn Variable>]) {
    for target in 0..variables.len() {
        let known: Vec<Option<&dyn Variable>> = (0..variables.len())
            .map(|k| (k != target).then(|| variables[k].as_ref()))
            .collect();
        let Some(predicted) = factor.predict(&known, target) else {
            continue;
        };
        let refs: Vec<&dyn Variable> = (0..variables.len())
            .map(|k| {
                if k == target {
                    predicted.as_ref()
                } else {
                    variables[k].as_ref()
                }
            })
            .collect();
        let mut e = vec![0.0; factor.residual_dim()];
        factor
            .evaluate(&refs, &mut e, None)
            .expect("evaluation failed");
        assert!(
            e.iter().all(|v| v.abs() < 1e-9),
            "{}: predicting variable {target} leaves error {e:?}",
            factor.name()
        );
    }
}
