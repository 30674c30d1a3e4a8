//! A factor as the problem holds it: the residual, its weight, its kernel, a label, and the dense
//! indices of the variables it touches.

use crate::factors::{EvaluationError, Factor, RobustKernel, SqrtInformation};
use crate::variables::Variable;

/// A factor in a problem: the residual function, its weight, its kernel, and a label naming it in
/// errors (e.g. `EDGE_SE2 3 7 (intel-e.dat:12)`).
#[derive(Debug)]
pub struct FactorEntry {
    pub factor: Box<dyn Factor>,
    pub sqrt_information: SqrtInformation,
    pub robust: Option<RobustKernel>,
    pub label: String,
    /// Dense indices (into the problem's `Values`) of `factor.keys()`, resolved once on insertion
    /// so the solver never hashes a key.
    pub(crate) variables: Vec<usize>,
}

impl FactorEntry {
    /// Indices into the problem's `Values` of the variables this factor touches, in key order.
    pub fn variables(&self) -> &[usize] {
        &self.variables
    }

    /// Whitened, robustified squared error `ρ(‖R e‖²)` at `variables` (the chi2 contribution).
    pub fn chi2(
        &self,
        variables: &[&dyn Variable],
        error_buffer: &mut [f64],
        whitened: &mut [f64],
    ) -> Result<f64, EvaluationError> {
        self.factor.evaluate(variables, error_buffer, None)?;
        self.sqrt_information.whiten_vector(error_buffer, whitened);
        let s: f64 = whitened.iter().map(|v| v * v).sum();
        Ok(match &self.robust {
            Some(k) => k.evaluate(s).rho,
            None => s,
        })
    }
}
