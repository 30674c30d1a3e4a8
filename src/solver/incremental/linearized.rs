//! Each factor's linearisation at the engine's linearisation point θ, kept until one of its
//! variables is relinearised: its Gram matrix `JᵀJ`, its gradient `Jᵀr` (both whitened and
//! robustified as in `solver::linearize`) and its chi2 at θ. The normal equations of the whole
//! problem are sums of these blocks, so a column of `H` is rebuilt from the factors touching
//! one variable without linearising anything else.

use crate::factors::EvaluationError;
use crate::problem::FactorEntry;
use crate::solver::linearize::{factor_normal_equations, Scratch};
use crate::variables::Variable;

/// One factor linearised at θ.
#[derive(Debug, Default, Clone)]
pub struct Linearized {
    /// `JᵀJ`, `cols × cols` row-major, both triangles.
    pub gram: Vec<f64>,
    /// `Jᵀr` (the normal equations' right-hand side is its negative).
    pub gradient: Vec<f64>,
    /// First column of each variable in `gram`, in the factor's key order; `cols` last.
    pub col_offset: Vec<usize>,
    /// Robustified chi2 at θ.
    pub chi2: f64,
}

impl Linearized {
    pub fn cols(&self) -> usize {
        self.gradient.len()
    }
}

/// Linearises `entry` at `theta` (indexed like the problem's values) into `out`, with the batch
/// solver's per-factor kernel (`solver::linearize::factor_normal_equations`).
pub fn linearize_factor(
    entry: &FactorEntry,
    theta: &[Box<dyn Variable>],
    scratch: &mut Scratch,
    out: &mut Linearized,
) -> Result<(), EvaluationError> {
    let refs: Vec<&dyn Variable> = entry
        .variables()
        .iter()
        .map(|&v| theta[v].as_ref())
        .collect();
    out.col_offset.clear();
    let mut cols = 0;
    for r in &refs {
        out.col_offset.push(cols);
        cols += r.tangent_dim();
    }
    out.col_offset.push(cols);
    let (chi2, gram, gradient) = factor_normal_equations(entry, &refs, scratch)?;
    out.chi2 = chi2;
    out.gram.clear();
    out.gram.extend_from_slice(gram);
    out.gradient.clear();
    out.gradient.extend_from_slice(gradient);
    Ok(())
}

/// Linearises the factors `pending` (indices into `entries`) again at `theta`, into their
/// entries of `linearized`; returns by how much their chi2 at θ changed.
pub fn relinearize_factors(
    pending: &[usize],
    entries: &[FactorEntry],
    theta: &[Box<dyn Variable>],
    scratch: &mut Scratch,
    linearized: &mut [Linearized],
) -> Result<f64, EvaluationError> {
    let mut change = 0.0;
    for &f in pending {
        let lin = &mut linearized[f];
        change -= lin.chi2;
        linearize_factor(&entries[f], theta, scratch, lin)?;
        change += lin.chi2;
    }
    Ok(change)
}
