//! `NonlinearFactorGraph`, and the library problem a graph and a `Values` make together.

use std::sync::Arc;

use pyo3::exceptions::PyIndexError;
use pyo3::prelude::*;

use factord::problem::{Gauge, Key, Problem};

use crate::errors::{chi2_of, problem_error, FactordError};
use crate::factors::{factor_object, FactorData, NonlinearFactor};
use crate::noise::NoiseModel;
use crate::planar::Pose2;
use crate::spatial::Pose3;
use crate::values::Values;

#[pyclass(module = "factord", name = "NonlinearFactorGraph")]
#[derive(Clone, Debug, Default)]
pub struct NonlinearFactorGraph {
    /// `None` where a factor was removed (GTSAM keeps the slot, so indices stay).
    pub factors: Vec<Option<Arc<FactorData>>>,
}

impl NonlinearFactorGraph {
    pub fn present(&self) -> impl Iterator<Item = &Arc<FactorData>> {
        self.factors.iter().flatten()
    }
}

/// The library problem of `values` (in key order) and `factors`. The gauge is free, as GTSAM's:
/// a graph without a prior is singular for Gauss-Newton, and says so.
pub fn build_problem<'a>(
    values: &Values,
    factors: impl IntoIterator<Item = &'a Arc<FactorData>>,
) -> PyResult<Problem> {
    let mut problem = Problem::with_gauge(Gauge::Free);
    // Cameras and points (bundle adjustment): the points are eliminated first (the Schur
    // complement), as `factord ba` and a BAL file's problem do.
    if values.map.values().any(|v| v.kind() == "snavely_camera") {
        problem.eliminate = vec!["point3"];
    }
    for (&key, v) in &values.map {
        problem
            .add_variable(key, v.clone_box())
            .map_err(problem_error)?;
    }
    for data in factors {
        add_factor(&mut problem, data)?;
    }
    Ok(problem)
}

/// Adds one graph factor to a problem (its variables checked there). Its residual is not
/// evaluated here: the solver evaluates the initial cost first and refuses a non-finite one,
/// and evaluating every factor twice was a quarter of an in-process solve of intel.
pub fn add_factor(problem: &mut Problem, data: &Arc<FactorData>) -> PyResult<usize> {
    let factor = match crate::custom::with_kinds(problem, data)? {
        Some(factor) => factor.into(),
        None => Arc::clone(&data.factor),
    };
    problem
        .add_checked_factor_sqrt(
            factor,
            data.sqrt_information.clone(),
            data.robust,
            data.label.clone(),
        )
        .map_err(problem_error)
}

/// `½ ρ(‖R e‖²)` of one factor at `values`.
pub fn factor_error(data: &Arc<FactorData>, values: &Values) -> PyResult<f64> {
    let mut only: Values = Values::default();
    for &k in data.factor.keys() {
        only.map.insert(k, values.get(k)?.clone_box());
    }
    let problem = build_problem(&only, [data])?;
    Ok(0.5 * chi2_of(&problem)?)
}

#[pymethods]
impl NonlinearFactorGraph {
    #[new]
    #[pyo3(signature = (other = None))]
    fn new(other: Option<&NonlinearFactorGraph>) -> Self {
        other.cloned().unwrap_or_default()
    }
    /// Appends a factor (GTSAM: `add`).
    fn add(&mut self, factor: PyRef<'_, NonlinearFactor>) {
        self.factors.push(Some(factor.data.clone()));
    }
    /// Appends a factor, or every factor of another graph.
    fn push_back(&mut self, item: &Bound<'_, PyAny>) -> PyResult<()> {
        if let Ok(factor) = item.extract::<PyRef<'_, NonlinearFactor>>() {
            self.factors.push(Some(factor.data.clone()));
            return Ok(());
        }
        let other: PyRef<'_, NonlinearFactorGraph> = item.extract()?;
        self.factors.extend(other.factors.iter().cloned());
        Ok(())
    }
    #[pyo3(name = "addPriorPose2")]
    fn add_prior_pose2(
        &mut self,
        py: Python<'_>,
        key: Key,
        prior: Pose2,
        noise: &NoiseModel,
    ) -> PyResult<()> {
        let data = FactorData::new(
            Box::new(factord::factors::PriorSe2::new(key, prior.inner)),
            noise,
            crate::factors::FactorClass::PriorFactorPose2,
            Some(Py::new(py, prior)?.into_bound(py).into_any()),
        )?;
        self.factors.push(Some(Arc::new(data)));
        Ok(())
    }
    #[pyo3(name = "addPriorPose3")]
    fn add_prior_pose3(
        &mut self,
        py: Python<'_>,
        key: Key,
        prior: Pose3,
        noise: &NoiseModel,
    ) -> PyResult<()> {
        let data = FactorData::new(
            Box::new(factord::factors::PriorSe3::new(key, prior.inner)),
            noise,
            crate::factors::FactorClass::PriorFactorPose3,
            Some(Py::new(py, prior)?.into_bound(py).into_any()),
        )?;
        self.factors.push(Some(Arc::new(data)));
        Ok(())
    }
    /// Number of slots, removed ones included (GTSAM's `size`).
    fn size(&self) -> usize {
        self.factors.len()
    }
    fn __len__(&self) -> usize {
        self.factors.len()
    }
    /// Number of factors present.
    #[pyo3(name = "nrFactors")]
    fn nr_factors(&self) -> usize {
        self.present().count()
    }
    fn empty(&self) -> bool {
        self.factors.is_empty()
    }
    /// The factor at `index`, or `None` where one was removed.
    fn at(&self, py: Python<'_>, index: usize) -> PyResult<Py<PyAny>> {
        match self.factors.get(index) {
            Some(Some(data)) => factor_object(py, data),
            Some(None) => Ok(py.None()),
            None => Err(PyIndexError::new_err(format!(
                "factor index {index} is beyond the graph's {} slots",
                self.factors.len()
            ))),
        }
    }
    fn __getitem__(&self, py: Python<'_>, index: usize) -> PyResult<Py<PyAny>> {
        self.at(py, index)
    }
    fn exists(&self, index: usize) -> bool {
        matches!(self.factors.get(index), Some(Some(_)))
    }
    /// Empties the slot `index` (the others keep their indices).
    fn remove(&mut self, index: usize) -> PyResult<()> {
        match self.factors.get_mut(index) {
            Some(slot) => {
                *slot = None;
                Ok(())
            }
            None => Err(PyIndexError::new_err(format!(
                "factor index {index} is beyond the graph's {} slots",
                self.factors.len()
            ))),
        }
    }
    /// Every key a factor touches, ascending.
    fn keys(&self) -> Vec<Key> {
        let mut keys: Vec<Key> = self
            .present()
            .flat_map(|f| f.factor.keys().iter().copied())
            .collect();
        keys.sort_unstable();
        keys.dedup();
        keys
    }
    /// `½ Σ ρ(‖R e‖²)` at `values` (GTSAM's graph error).
    fn error(&self, values: &Values) -> PyResult<f64> {
        let mut needed = Values::default();
        for key in self.keys() {
            needed.map.insert(key, values.get(key)?.clone_box());
        }
        let problem = build_problem(&needed, self.present())?;
        let chi2 = chi2_of(&problem)?;
        if !chi2.is_finite() {
            return Err(FactordError::new_err(
                "the graph's error is not finite at these values",
            ));
        }
        Ok(0.5 * chi2)
    }
    fn clone(&self) -> Self {
        Clone::clone(self)
    }
    fn __repr__(&self) -> String {
        format!("NonlinearFactorGraph with {} factors", self.nr_factors())
    }
}
