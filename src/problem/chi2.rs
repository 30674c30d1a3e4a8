//! The cost `Σ ρ(‖R e‖²)` of a set of factors at an estimate.

use std::borrow::Borrow;
use std::ops::ControlFlow;

use super::{FactorEntry, Values};
use crate::factors::EvaluationError;
use crate::variables::Variable;

/// `Σ ρ(eᵀΩe)` over `factors` at `values`.
pub fn evaluate_chi2<E: Borrow<FactorEntry>>(
    factors: &[E],
    values: &Values,
) -> Result<f64, EvaluationError> {
    match evaluate_chi2_checked(factors, values, |_| ControlFlow::Continue(()))? {
        ControlFlow::Continue(chi2) => Ok(chi2),
        ControlFlow::Break(()) => unreachable!("a checkpoint that never breaks stopped the sum"),
    }
}

/// [`evaluate_chi2`] that asks `checkpoint(k)` before the `k`-th factor whether to go on (the
/// solver's time budget stops long sums this way).
pub fn evaluate_chi2_checked<E: Borrow<FactorEntry>>(
    factors: &[E],
    values: &Values,
    mut checkpoint: impl FnMut(usize) -> ControlFlow<()>,
) -> Result<ControlFlow<(), f64>, EvaluationError> {
    let mut total = 0.0;
    let mut scratch = Chi2Scratch::default();
    for (k, f) in factors.iter().enumerate() {
        if checkpoint(k).is_break() {
            return Ok(ControlFlow::Break(()));
        }
        total += scratch.chi2(f.borrow(), values)?;
    }
    Ok(ControlFlow::Continue(total))
}

/// Buffers for evaluating factor after factor at the same values without allocating.
#[derive(Default)]
pub struct Chi2Scratch<'v> {
    variables: Vec<&'v dyn Variable>,
    error: Vec<f64>,
    whitened: Vec<f64>,
}

impl<'v> Chi2Scratch<'v> {
    /// `ρ(‖R e‖²)` of `factor` at `values`.
    pub fn chi2(
        &mut self,
        factor: &FactorEntry,
        values: &'v Values,
    ) -> Result<f64, EvaluationError> {
        self.variables.clear();
        self.variables
            .extend(factor.variables().iter().map(|&v| values.variable(v)));
        let d = factor.factor.residual_dim();
        self.error.resize(d, 0.0);
        self.whitened.resize(d, 0.0);
        factor.chi2(&self.variables, &mut self.error, &mut self.whitened)
    }
}
