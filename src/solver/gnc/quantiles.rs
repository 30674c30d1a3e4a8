//! χ² quantiles cached per residual dimension: the thresholds of every decision.

use crate::solver::chi_square::chi_square_quantile;

/// χ² quantiles at one confidence, computed once per residual dimension (a bisection each: a
/// few hundred microseconds, which per factor cost a 1500-pose job 0.1 s before its solve).
pub(super) struct Quantiles {
    confidence: f64,
    by_dof: std::cell::RefCell<Vec<Option<f64>>>,
}

impl Quantiles {
    pub(super) fn new(confidence: f64) -> Self {
        Self {
            confidence,
            by_dof: std::cell::RefCell::new(Vec::new()),
        }
    }

    pub(super) fn of(&self, dof: usize) -> f64 {
        let mut cache = self.by_dof.borrow_mut();
        if cache.len() <= dof {
            cache.resize(dof + 1, None);
        }
        *cache[dof].get_or_insert_with(|| chi_square_quantile(dof, self.confidence))
    }
}
