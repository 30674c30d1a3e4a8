//! `ISAM2`: factors and values arrive update by update and the library's incremental engine
//! (`solver::incremental`, the one a server session runs) refactors only what each touches.

use std::sync::Arc;

use pyo3::prelude::*;

use factord::problem::{Gauge, Key, Problem};
use factord::solver::incremental::{IncrementalEngine, UpdateParams};

use crate::errors::{problem_error, solver_error, ValuesKeyAlreadyExists};
use crate::graph::{add_factor, NonlinearFactorGraph};
use crate::keys::key_name;
use crate::marginals::Marginals;
use crate::optimizers::values_of;
use crate::values::Values;

#[pyclass(module = "factord", name = "ISAM2Params", from_py_object)]
#[derive(Clone, Debug)]
pub struct ISAM2Params {
    /// A variable is relinearised when its step's largest component exceeds this (GTSAM's
    /// default 0.1).
    #[pyo3(get, set, name = "relinearizeThreshold")]
    pub relinearize_threshold: f64,
    /// Accepted for GTSAM scripts; factord checks every update for relinearisation.
    #[pyo3(get, set, name = "relinearizeSkip")]
    pub relinearize_skip: usize,
}

#[pymethods]
impl ISAM2Params {
    #[new]
    fn new() -> Self {
        Self {
            relinearize_threshold: 0.1,
            relinearize_skip: 10,
        }
    }
    #[pyo3(name = "setRelinearizeThreshold")]
    fn set_relinearize_threshold(&mut self, threshold: f64) {
        self.relinearize_threshold = threshold;
    }
    #[pyo3(name = "getRelinearizeThreshold")]
    fn get_relinearize_threshold(&self) -> f64 {
        self.relinearize_threshold
    }
    #[pyo3(name = "setRelinearizeSkip")]
    fn set_relinearize_skip(&mut self, skip: usize) {
        self.relinearize_skip = skip;
    }
}

/// What one update did (GTSAM: `ISAM2Result`, the counts factord has).
#[pyclass(module = "factord", name = "ISAM2Result", get_all)]
pub struct ISAM2Result {
    #[pyo3(name = "variablesRelinearized")]
    pub variables_relinearized: usize,
    #[pyo3(name = "variablesReeliminated")]
    pub variables_reeliminated: usize,
    #[pyo3(name = "newFactors")]
    pub new_factors: usize,
    #[pyo3(name = "newVariables")]
    pub new_variables: usize,
    pub passes: usize,
    pub seconds: f64,
}

#[pymethods]
impl ISAM2Result {
    #[pyo3(name = "getVariablesRelinearized")]
    fn get_variables_relinearized(&self) -> usize {
        self.variables_relinearized
    }
    #[pyo3(name = "getVariablesReeliminated")]
    fn get_variables_reeliminated(&self) -> usize {
        self.variables_reeliminated
    }
}

#[pyclass(module = "factord", name = "ISAM2", unsendable)]
pub struct ISAM2 {
    problem: Problem,
    graph: NonlinearFactorGraph,
    /// `None` before the first update and after a failed one (the next update rebuilds it).
    engine: Option<IncrementalEngine>,
    params: UpdateParams,
}

#[pymethods]
impl ISAM2 {
    #[new]
    #[pyo3(signature = (params = None))]
    fn new(params: Option<ISAM2Params>) -> PyResult<Self> {
        let p = params.unwrap_or_else(ISAM2Params::new);
        if !(p.relinearize_threshold.is_finite() && p.relinearize_threshold > 0.0) {
            return Err(crate::errors::FactordError::new_err(format!(
                "ISAM2Params.relinearizeThreshold must be finite and > 0, got {}",
                p.relinearize_threshold
            )));
        }
        Ok(Self {
            problem: Problem::with_gauge(Gauge::Free),
            graph: NonlinearFactorGraph::default(),
            engine: None,
            params: UpdateParams {
                relinearize_threshold: p.relinearize_threshold,
                ..UpdateParams::default()
            },
        })
    }

    /// Adds the new variables (initial guesses) and factors, then relinearises and solves what
    /// they touch. Every new factor's variables must be known by then.
    #[pyo3(signature = (new_factors = None, new_theta = None))]
    fn update(
        &mut self,
        py: Python<'_>,
        new_factors: Option<&NonlinearFactorGraph>,
        new_theta: Option<&Values>,
    ) -> PyResult<ISAM2Result> {
        let start = std::time::Instant::now();
        if let Some(values) = new_theta {
            if let Some(&k) = values
                .map
                .keys()
                .find(|&&k| self.problem.values.index_of(k).is_some())
            {
                return Err(ValuesKeyAlreadyExists::new_err(format!(
                    "ISAM2.update: variable {} is already in the estimate",
                    key_name(k)
                )));
            }
        }
        // Check the new factors against the variables there will be before changing anything.
        let known = |k: Key| {
            self.problem.values.index_of(k).is_some()
                || new_theta.is_some_and(|v| v.map.contains_key(&k))
        };
        if let Some(graph) = new_factors {
            for f in graph.present() {
                if let Some(&k) = f.factor.keys().iter().find(|&&k| !known(k)) {
                    return Err(crate::errors::ValuesKeyDoesNotExist::new_err(format!(
                        "{}: no estimate or new value for variable {}",
                        f.label,
                        key_name(k)
                    )));
                }
            }
        }
        if let Some(values) = new_theta {
            for (&k, v) in &values.map {
                self.problem
                    .add_variable(k, v.clone_box())
                    .map_err(problem_error)?;
            }
        }
        if let Some(graph) = new_factors {
            for f in graph.present() {
                add_factor(&mut self.problem, f)?;
                self.graph.factors.push(Some(Arc::clone(f)));
            }
        }
        // Without the GIL: a `CustomFactor` relinearised on the engine's second thread takes it.
        let (engine, problem, params) = (&mut self.engine, &mut self.problem, &self.params);
        let report = py.detach(|| match engine.as_mut() {
            Some(engine) => engine.update(problem, params),
            None => {
                let fixed = vec![false; problem.values.len()];
                IncrementalEngine::new(problem, &fixed).map(|(new, report)| {
                    *engine = Some(new);
                    report
                })
            }
        });
        let report = match report {
            Ok(r) => r,
            Err(e) => {
                self.engine = None;
                return Err(solver_error(e));
            }
        };
        Ok(ISAM2Result {
            variables_relinearized: report.relinearized_variables,
            variables_reeliminated: report.refactored_columns,
            new_factors: report.new_factors,
            new_variables: report.new_variables,
            passes: report.passes,
            seconds: start.elapsed().as_secs_f64(),
        })
    }

    #[pyo3(name = "calculateEstimate")]
    fn calculate_estimate(&self) -> Values {
        values_of(&self.problem)
    }
    #[pyo3(name = "calculateBestEstimate")]
    fn calculate_best_estimate(&self) -> Values {
        values_of(&self.problem)
    }
    #[pyo3(name = "calculateEstimatePose2")]
    fn calculate_estimate_pose2(&self, key: Key) -> PyResult<crate::planar::Pose2> {
        let v = values_of(&self.problem);
        Ok(crate::planar::Pose2::from_se2(
            *v.get_as::<factord::geometry::Se2>(key, "Pose2")?,
        ))
    }
    #[pyo3(name = "calculateEstimatePose3")]
    fn calculate_estimate_pose3(&self, key: Key) -> PyResult<crate::spatial::Pose3> {
        let v = values_of(&self.problem);
        Ok(crate::spatial::Pose3::from_se3(
            *v.get_as::<factord::geometry::Se3>(key, "Pose3")?,
        ))
    }
    /// Every factor given so far.
    #[pyo3(name = "getFactorsUnsafe")]
    fn get_factors_unsafe(&self) -> NonlinearFactorGraph {
        self.graph.clone()
    }
    /// The covariance of `key` at the current estimate (GTSAM's conventions, see `Marginals`).
    #[pyo3(name = "marginalCovariance")]
    fn marginal_covariance<'py>(&self, py: Python<'py>, key: Key) -> PyResult<Bound<'py, PyAny>> {
        let values = values_of(&self.problem);
        let problem = crate::graph::build_problem(&values, self.graph.present())?;
        let m = Marginals::of_problem(problem)?;
        m.marginal_covariance_of(py, key)
    }
    /// `½ Σ ρ` of every factor at the current estimate.
    fn error(&self) -> PyResult<f64> {
        Ok(0.5 * crate::errors::chi2_of(&self.problem)?)
    }
}
