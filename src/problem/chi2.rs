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
    let mut e = Vec::new();
    let mut w = Vec::new();
    let mut refs: Vec<&dyn Variable> = Vec::with_capacity(8);
    for (k, f) in factors.iter().enumerate() {
        if checkpoint(k).is_break() {
            return Ok(ControlFlow::Break(()));
        }
        let f = f.borrow();
        refs.clear();
        refs.extend(f.variables().iter().map(|&v| values.variable(v)));
        let d = f.factor.residual_dim();
        e.resize(d, 0.0);
        w.resize(d, 0.0);
        total += f.chi2(&refs, &mut e, &mut w)?;
    }
    Ok(ControlFlow::Continue(total))
}
