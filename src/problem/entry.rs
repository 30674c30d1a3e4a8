//! A factor as the problem holds it: the residual, its weight, its kernel, a label, and the dense
//! indices of the variables it touches.

use std::sync::Arc;

use crate::factors::{EvaluationError, Factor, RobustKernel, SqrtInformation};
use crate::variables::Variable;

/// A factor in a problem: the residual function, its weight, its kernel, and a label naming it in
/// errors (e.g. `EDGE_SE2 3 7 (intel-e.dat:12)`). A clone shares the factor.
#[derive(Clone, Debug)]
pub struct FactorEntry {
    /// Shared: a factor is not `Clone` (user-defined ones hold compiled tapes), and a copy of
    /// the problem (a session's relinearisation beside its updates) or a session's window of
    /// recent factors holds the same one.
    pub factor: Arc<dyn Factor>,
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

    /// Estimated bytes this entry holds: the entry, the boxed factor (about 96 bytes), the
    /// square-root information, the variable indices and the label. An estimate from sizes,
    /// not an allocator count; a problem keeps the sum as factors come and go.
    pub fn estimated_bytes(&self) -> usize {
        let r = self.factor.residual_dim();
        std::mem::size_of::<FactorEntry>()
            + 96
            + 8 * (r * r + self.variables.len())
            + self.label.len()
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
