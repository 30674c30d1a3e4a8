//! A nonlinear least-squares problem: variables under 64-bit keys, and factors over them.
//!
//! Everything that enters is validated here once (keys exist, kinds match, dimensions agree,
//! information is positive definite, numbers are finite), so the solver can trust what it gets.
//!
//! Layer 3: imports `variables` and `factors`; the solver builds on it, never the other way.

mod chi2;
mod entry;
mod values;

pub use chi2::{evaluate_chi2, evaluate_chi2_checked, Chi2Scratch};
pub use entry::FactorEntry;

pub use values::Values;

pub use crate::variables::{Key, Variable};

use std::sync::Arc;

use nalgebra::DMatrix;

use crate::factors::{Factor, RobustKernel, SqrtInformation};

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ProblemError {
    #[error("variable {key} already exists")]
    DuplicateVariable { key: Key },
    #[error("variable {key} has a non-finite value")]
    NonFiniteVariable { key: Key },
    #[error("unknown variable {key}")]
    UnknownVariable { key: Key },
    #[error("{factor}: refers to unknown variable {key}")]
    FactorUnknownVariable { factor: String, key: Key },
    #[error("{factor}: variable {key} is of kind {found}, the factor needs {expected}")]
    FactorWrongKind {
        factor: String,
        key: Key,
        expected: &'static str,
        found: &'static str,
    },
    #[error("{factor}: touches variable {key} twice")]
    FactorRepeatedVariable { factor: String, key: Key },
    #[error("{factor}: information matrix is invalid: {reason}")]
    BadInformation {
        factor: String,
        reason: crate::factors::noise::InformationError,
    },
    #[error("{factor}: measurement is not finite")]
    NonFiniteMeasurement { factor: String },
}

/// A clone copies the values and shares the factors (see [`FactorEntry`]).
#[derive(Clone, Debug, Default)]
pub struct Problem {
    pub values: Values,
    factors: Vec<FactorEntry>,
    /// How the solver removes gauge freedom.
    pub gauge: Gauge,
    /// Kinds of landmark-like variables the linear solver eliminates first by Schur complement
    /// (`"point3"` in bundle adjustment). Empty: none.
    pub eliminate: Vec<&'static str>,
    /// Σ [`FactorEntry::estimated_bytes`] over `factors`, kept as they are added and removed so
    /// a size estimate never walks the problem.
    factor_bytes: usize,
}

/// What the solver does about directions in which the cost is flat as a whole (a pose graph
/// without priors can slide and turn; a bundle adjustment can also scale).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Gauge {
    /// Fix the lowest key of every connected component that has no fixed variable and no prior
    /// (pose graphs: the result is then reproducible and Gauss-Newton well posed).
    #[default]
    AnchorComponents,
    /// Fix nothing: damping (LM, Dogleg) keeps the flat directions in check, as Ceres does for
    /// bundle adjustment, where fixing a whole camera would also freeze its intrinsics.
    Free,
}

impl Problem {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn with_gauge(gauge: Gauge) -> Self {
        Self {
            gauge,
            ..Self::default()
        }
    }

    /// This problem with `kinds` eliminated first by the linear solver (see [`Problem::eliminate`]).
    pub fn eliminating(mut self, kinds: &[&'static str]) -> Self {
        self.eliminate = kinds.to_vec();
        self
    }

    pub fn add_variable(
        &mut self,
        key: Key,
        variable: Box<dyn Variable>,
    ) -> Result<usize, ProblemError> {
        if !variable.is_finite() {
            return Err(ProblemError::NonFiniteVariable { key });
        }
        self.values
            .insert(key, variable)
            .ok_or(ProblemError::DuplicateVariable { key })
    }

    pub fn set_fixed(&mut self, key: Key, fixed: bool) -> Result<(), ProblemError> {
        let idx = self
            .values
            .index_of(key)
            .ok_or(ProblemError::UnknownVariable { key })?;
        self.values.set_fixed(idx, fixed);
        Ok(())
    }

    /// Adds a factor weighted by the information matrix `information` (residual_dim × residual_dim).
    pub fn add_factor(
        &mut self,
        factor: Box<dyn Factor>,
        information: &DMatrix<f64>,
        robust: Option<RobustKernel>,
        label: impl Into<String>,
    ) -> Result<usize, ProblemError> {
        let label = label.into();
        let sqrt_information =
            SqrtInformation::from_information(information).map_err(|reason| {
                ProblemError::BadInformation {
                    factor: label.clone(),
                    reason,
                }
            })?;
        if sqrt_information.dim() != factor.residual_dim() {
            return Err(ProblemError::BadInformation {
                factor: label,
                reason: crate::factors::noise::InformationError::WrongSize {
                    rows: information.nrows(),
                    cols: information.ncols(),
                    expected: factor.residual_dim(),
                },
            });
        }
        self.add_factor_sqrt(factor, sqrt_information, robust, label)
    }

    pub fn add_factor_sqrt(
        &mut self,
        factor: Box<dyn Factor>,
        sqrt_information: SqrtInformation,
        robust: Option<RobustKernel>,
        label: String,
    ) -> Result<usize, ProblemError> {
        self.push_factor(factor.into(), sqrt_information, robust, label, true)
    }

    /// As [`Problem::add_factor_sqrt`] for a factor another problem or a session's window
    /// also holds.
    pub fn add_shared_factor_sqrt(
        &mut self,
        factor: Arc<dyn Factor>,
        sqrt_information: SqrtInformation,
        robust: Option<RobustKernel>,
        label: String,
    ) -> Result<usize, ProblemError> {
        self.push_factor(factor, sqrt_information, robust, label, true)
    }

    /// As [`Problem::add_factor_sqrt`] without evaluating the factor: for a session's factors,
    /// which were checked at the client's values and must be added even if a solve has since
    /// moved them somewhere the residual is not finite (that solve then fails, visibly).
    pub fn add_checked_factor_sqrt(
        &mut self,
        factor: Arc<dyn Factor>,
        sqrt_information: SqrtInformation,
        robust: Option<RobustKernel>,
        label: String,
    ) -> Result<usize, ProblemError> {
        self.push_factor(factor, sqrt_information, robust, label, false)
    }

    /// Adds the factor once its variables check out and, with `evaluate`, once its residual at
    /// the current values is finite; its index.
    fn push_factor(
        &mut self,
        factor: Arc<dyn Factor>,
        sqrt_information: SqrtInformation,
        robust: Option<RobustKernel>,
        label: String,
        evaluate: bool,
    ) -> Result<usize, ProblemError> {
        let variables = self.resolve(factor.as_ref(), &label)?;
        if evaluate {
            // A factor that cannot be evaluated at a finite point has a non-finite measurement.
            let vars: Vec<&dyn Variable> =
                variables.iter().map(|&v| self.values.variable(v)).collect();
            if !crate::factors::residual_is_finite(factor.as_ref(), &vars) {
                return Err(ProblemError::NonFiniteMeasurement { factor: label });
            }
        }
        Ok(self.push_entry(FactorEntry {
            factor,
            sqrt_information,
            robust,
            label,
            variables,
        }))
    }

    /// The entry [`Problem::add_checked_factor_sqrt`] would add, without adding it: for a
    /// factor weighed against the problem before it may enter (a possibly wrong loop closure).
    pub fn detached_entry(
        &self,
        factor: Arc<dyn Factor>,
        sqrt_information: SqrtInformation,
        robust: Option<RobustKernel>,
        label: String,
    ) -> Result<FactorEntry, ProblemError> {
        let variables = self.resolve(factor.as_ref(), &label)?;
        Ok(FactorEntry {
            factor,
            sqrt_information,
            robust,
            label,
            variables,
        })
    }

    /// Adds an entry made by [`Problem::detached_entry`] of this problem; its index.
    pub fn push_entry(&mut self, entry: FactorEntry) -> usize {
        self.factor_bytes += entry.estimated_bytes();
        self.factors.push(entry);
        self.factors.len() - 1
    }

    /// Takes the factors for which `take(index)` is true out of the problem, in order; the
    /// others keep their order.
    pub fn take_factors(&mut self, mut take: impl FnMut(usize) -> bool) -> Vec<FactorEntry> {
        let all = std::mem::take(&mut self.factors);
        let mut taken = Vec::new();
        for (i, entry) in all.into_iter().enumerate() {
            if take(i) {
                self.factor_bytes -= entry.estimated_bytes();
                taken.push(entry);
            } else {
                self.factors.push(entry);
            }
        }
        taken
    }

    /// Checks the variables `factor` touches (exist, distinct, right kinds); their indices.
    /// One lookup per key: building a problem resolves every factor's keys.
    fn resolve(&self, factor: &dyn Factor, label: &str) -> Result<Vec<usize>, ProblemError> {
        let keys = factor.keys();
        let kinds = factor.variable_kinds();
        let mut variables = Vec::with_capacity(keys.len());
        for (pos, &key) in keys.iter().enumerate() {
            if keys[..pos].contains(&key) {
                return Err(ProblemError::FactorRepeatedVariable {
                    factor: label.to_string(),
                    key,
                });
            }
            let index =
                self.values
                    .index_of(key)
                    .ok_or_else(|| ProblemError::FactorUnknownVariable {
                        factor: label.to_string(),
                        key,
                    })?;
            let found = self.values.variable(index).kind();
            match kinds.get(pos) {
                Some(&expected) if expected != found => {
                    return Err(ProblemError::FactorWrongKind {
                        factor: label.to_string(),
                        key,
                        expected,
                        found,
                    });
                }
                _ => {}
            }
            variables.push(index);
        }
        Ok(variables)
    }

    pub fn factors(&self) -> &[FactorEntry] {
        &self.factors
    }

    /// The factors, to reweight in place (their variables and sizes stay as they are).
    pub(crate) fn factors_mut(&mut self) -> &mut [FactorEntry] {
        &mut self.factors
    }

    /// Keeps the factors for which `keep(index)` is true, in order.
    pub fn retain_factors(&mut self, mut keep: impl FnMut(usize) -> bool) {
        let mut index = 0;
        let mut removed_bytes = 0;
        self.factors.retain(|f| {
            index += 1;
            let kept = keep(index - 1);
            if !kept {
                removed_bytes += f.estimated_bytes();
            }
            kept
        });
        self.factor_bytes -= removed_bytes;
    }

    /// Estimated bytes the factors hold (Σ [`FactorEntry::estimated_bytes`]), in O(1).
    pub fn factor_bytes(&self) -> usize {
        self.factor_bytes
    }

    /// Sets every factor's robust kernel (the CLI's `--robust`).
    pub fn set_robust_kernel(&mut self, kernel: Option<RobustKernel>) {
        for f in &mut self.factors {
            f.robust = kernel;
        }
    }

    /// Total chi2 `Σ ρ(eᵀ Ω e)` at the current values.
    pub fn chi2(&self) -> f64 {
        evaluate_chi2(self.factors(), &self.values).unwrap_or(f64::NAN)
    }
}
