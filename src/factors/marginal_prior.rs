//! The linear prior that marginalisation leaves behind:
//!
//! ```text
//! e = r₀ + J Δ,   Δ = (x_1 ⊖ x̄_1, …, x_k ⊖ x̄_k)
//! ```
//!
//! over the variables that shared a factor with the eliminated one, x̄ their values when it was
//! eliminated (the linearisation point) and ⊖ the inverse retraction ([`Variable::local`]).
//! Linearised, it contributes exactly the Schur complement `H* = JᵀJ`, `b* = −Jᵀ r₀` it was built
//! from (see [`crate::fusion::marginalize()`]). The Jacobian reported is `J` itself — the
//! first-estimate Jacobian: it is exact at x̄ and kept fixed as the variables move, so the
//! prior never claims information along directions the eliminated factors did not observe
//! (the inconsistency that re-linearising a marginal prior introduces).

use std::any::Any;

use nalgebra::{DMatrix, DVector};

use super::{EvaluationError, Factor};
use crate::variables::{Key, Variable};

#[derive(Debug)]
pub struct MarginalPrior {
    keys: Vec<Key>,
    kinds: Vec<&'static str>,
    linearization: Vec<Box<dyn Variable>>,
    /// m × n, n the sum of the variables' tangent dimensions.
    pub jacobian: DMatrix<f64>,
    pub residual: DVector<f64>,
}

impl MarginalPrior {
    /// `linearization[k]` is the value of `keys[k]` at which `jacobian` and `residual` hold.
    pub fn new(
        keys: Vec<Key>,
        linearization: Vec<Box<dyn Variable>>,
        jacobian: DMatrix<f64>,
        residual: DVector<f64>,
    ) -> Self {
        let kinds = linearization.iter().map(|v| v.kind()).collect();
        Self {
            keys,
            kinds,
            linearization,
            jacobian,
            residual,
        }
    }
}

/// The name MarginalPrior answers (internal: refused as a user-defined type name).
pub const NAME: &str = "marginal_prior";

impl Factor for MarginalPrior {
    fn name(&self) -> &'static str {
        NAME
    }
    fn keys(&self) -> &[Key] {
        &self.keys
    }
    fn residual_dim(&self) -> usize {
        self.residual.len()
    }
    fn variable_kinds(&self) -> &[&'static str] {
        &self.kinds
    }
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let n = self.jacobian.ncols();
        let mut delta = DVector::zeros(n);
        let mut offset = 0;
        for (k, (x, origin)) in variables.iter().zip(&self.linearization).enumerate() {
            let d = origin.tangent_dim();
            if !x.local(
                origin.as_ref(),
                &mut delta.as_mut_slice()[offset..offset + d],
            ) {
                return Err(EvaluationError::WrongKind {
                    position: k,
                    expected: origin.kind(),
                    found: x.kind(),
                });
            }
            offset += d;
        }
        let e = &self.residual + &self.jacobian * delta;
        error.copy_from_slice(e.as_slice());
        if let Some(j) = jacobian {
            for r in 0..self.jacobian.nrows() {
                for c in 0..n {
                    j[r * n + c] = self.jacobian[(r, c)];
                }
            }
        }
        Ok(())
    }
    fn as_any(&self) -> &dyn Any {
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::testing::{assert_jacobians_match, Rng};

    /// The first-estimate Jacobian is the true one at the linearisation point.
    #[test]
    fn jacobian_is_exact_at_the_linearization_point() {
        let mut rng = Rng::new(41);
        for _ in 0..20 {
            let (a, b) = (rng.nav_state(), rng.nav_state());
            let jacobian = DMatrix::from_fn(7, 30, |_, _| rng.normal());
            let residual = DVector::from_fn(7, |_, _| rng.normal());
            let prior = MarginalPrior::new(
                vec![3, 4],
                vec![Box::new(a), Box::new(b)],
                jacobian,
                residual.clone(),
            );
            assert_jacobians_match(&prior, &[Box::new(a), Box::new(b)]);
            let mut e = vec![0.0; 7];
            prior.evaluate(&[&a, &b], &mut e, None).unwrap();
            assert!((DVector::from_vec(e) - residual).amax() < 1e-12);
        }
    }
}
