//! Each factor's linearisation at the engine's linearisation point θ, kept until one of its
//! variables is relinearised: its Gram matrix `JᵀJ`, its gradient `Jᵀr` (both whitened and
//! robustified as in `solver::linearize`) and its chi2 at θ. The normal equations of the whole
//! problem are sums of these blocks, so a column of `H` is rebuilt from the factors touching
//! one variable without linearising anything else.

use crate::factors::EvaluationError;
use crate::problem::FactorEntry;
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

/// Scratch buffers reused across factors.
#[derive(Debug, Default)]
pub struct LinearizeScratch {
    error: Vec<f64>,
    residual: Vec<f64>,
    jacobian: Vec<f64>,
    whitened: Vec<f64>,
}

/// Linearises `entry` at `theta` (indexed like the problem's values) into `out`.
pub fn linearize_factor(
    entry: &FactorEntry,
    theta: &[Box<dyn Variable>],
    scratch: &mut LinearizeScratch,
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
    let d = entry.factor.residual_dim();
    let LinearizeScratch {
        error,
        residual,
        jacobian,
        whitened,
    } = scratch;
    error.resize(d, 0.0);
    residual.resize(d, 0.0);
    jacobian.resize(d * cols, 0.0);
    whitened.resize(d * cols, 0.0);
    entry.factor.evaluate(&refs, error, Some(jacobian))?;
    entry.sqrt_information.whiten_vector(error, residual);
    entry
        .sqrt_information
        .whiten_jacobian(jacobian, cols, whitened);
    out.chi2 = match &entry.robust {
        Some(kernel) => kernel.correct(residual, whitened, cols),
        None => residual.iter().map(|v| v * v).sum(),
    };
    out.gram.clear();
    out.gram.resize(cols * cols, 0.0);
    out.gradient.clear();
    out.gradient.resize(cols, 0.0);
    for (row, &rk) in whitened.chunks_exact(cols).zip(residual.iter()) {
        for (i, &ji) in row.iter().enumerate() {
            out.gradient[i] += ji * rk;
            for (g, &jj) in out.gram[i * cols..(i + 1) * cols].iter_mut().zip(row) {
                *g += ji * jj;
            }
        }
    }
    Ok(())
}
