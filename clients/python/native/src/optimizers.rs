//! `LevenbergMarquardtOptimizer`, `GaussNewtonOptimizer`, `DoglegOptimizer` and their params, as
//! GTSAM names them, over the library's batch solver; and `solve`, the library's own call, which
//! returns the Summary as `factord solve` prints it.

use pyo3::prelude::*;

use factord::problem::Problem;
use factord::solver::{self, Initialization, Method, SolverOptions, Summary};

use crate::errors::{solver_error, FactordError};
use crate::graph::{build_problem, NonlinearFactorGraph};
use crate::values::Values;

/// The settings every optimizer shares (GTSAM: `NonlinearOptimizerParams`).
#[pyclass(
    module = "factord",
    name = "NonlinearOptimizerParams",
    subclass,
    from_py_object
)]
#[derive(Clone, Debug)]
pub struct OptimizerParams {
    #[pyo3(get, set, name = "maxIterations")]
    pub max_iterations: usize,
    /// Stop when an iteration lowers the error by less than this fraction.
    #[pyo3(get, set, name = "relativeErrorTol")]
    pub relative_error_tol: f64,
    /// Accepted for GTSAM scripts; the library has no absolute-error criterion.
    #[pyo3(get, set, name = "absoluteErrorTol")]
    pub absolute_error_tol: f64,
    /// LM's initial damping (relative to diag(JᵀJ) in factord).
    #[pyo3(get, set, name = "lambdaInitial")]
    pub lambda_initial: f64,
    /// Dogleg's initial trust radius.
    #[pyo3(get, set, name = "deltaInitial")]
    pub delta_initial: f64,
    #[pyo3(get, set)]
    pub verbosity: String,
}

impl Default for OptimizerParams {
    fn default() -> Self {
        let ours = SolverOptions::default();
        Self {
            max_iterations: 100,
            relative_error_tol: 1e-5,
            absolute_error_tol: 1e-5,
            lambda_initial: ours.initial_lambda,
            delta_initial: 1.0,
            verbosity: "SILENT".into(),
        }
    }
}

impl OptimizerParams {
    fn options(&self, method: Method) -> PyResult<SolverOptions> {
        let options = SolverOptions {
            method,
            max_iterations: self.max_iterations,
            function_tolerance: self.relative_error_tol,
            initial_lambda: self.lambda_initial,
            initial_trust_radius: self.delta_initial,
            // GTSAM starts from the values it is given.
            initialization: Initialization::None,
            ..SolverOptions::default()
        };
        options
            .validate()
            .map_err(|(field, why)| FactordError::new_err(format!("params.{field}: {why}")))?;
        Ok(options)
    }
}

#[pymethods]
impl OptimizerParams {
    #[new]
    fn new() -> Self {
        Self::default()
    }
    #[pyo3(name = "setMaxIterations")]
    fn set_max_iterations(&mut self, n: usize) {
        self.max_iterations = n;
    }
    #[pyo3(name = "getMaxIterations")]
    fn get_max_iterations(&self) -> usize {
        self.max_iterations
    }
    #[pyo3(name = "setRelativeErrorTol")]
    fn set_relative_error_tol(&mut self, tol: f64) {
        self.relative_error_tol = tol;
    }
    #[pyo3(name = "getRelativeErrorTol")]
    fn get_relative_error_tol(&self) -> f64 {
        self.relative_error_tol
    }
    #[pyo3(name = "setAbsoluteErrorTol")]
    fn set_absolute_error_tol(&mut self, tol: f64) {
        self.absolute_error_tol = tol;
    }
    #[pyo3(name = "setlambdaInitial")]
    fn set_lambda_initial(&mut self, lambda: f64) {
        self.lambda_initial = lambda;
    }
    #[pyo3(name = "setDeltaInitial")]
    fn set_delta_initial(&mut self, delta: f64) {
        self.delta_initial = delta;
    }
    #[pyo3(name = "setVerbosity")]
    fn set_verbosity(&mut self, verbosity: String) {
        self.verbosity = verbosity;
    }
    #[pyo3(name = "setVerbosityLM")]
    fn set_verbosity_lm(&mut self, verbosity: String) {
        self.verbosity = verbosity;
    }
    /// Accepted and ignored: factord chooses its own fill-reducing ordering.
    #[pyo3(name = "setOrdering")]
    fn set_ordering(&mut self, _ordering: &Bound<'_, PyAny>) {}
}

/// The params classes GTSAM has, each a `NonlinearOptimizerParams`.
macro_rules! params_class {
    ($name:ident) => {
        #[pyclass(module = "factord", extends = OptimizerParams)]
        pub struct $name;

        #[pymethods]
        impl $name {
            #[new]
            fn new() -> PyClassInitializer<Self> {
                PyClassInitializer::from(OptimizerParams::default()).add_subclass($name)
            }
        }
    };
}
params_class!(LevenbergMarquardtParams);
params_class!(GaussNewtonParams);
params_class!(DoglegParams);

/// What an optimizer holds: the problem at its current values, and the last Summary.
pub struct Optimizer {
    problem: Problem,
    options: SolverOptions,
    summary: Option<Summary>,
}

impl Optimizer {
    fn new(
        graph: &NonlinearFactorGraph,
        initial: &Values,
        params: Option<&OptimizerParams>,
        method: Method,
    ) -> PyResult<Self> {
        let params = params.cloned().unwrap_or_default();
        Ok(Self {
            problem: build_problem(initial, graph.present())?,
            options: params.options(method)?,
            summary: None,
        })
    }

    fn optimize(&mut self, py: Python<'_>) -> PyResult<Values> {
        let summary = solve_detached(py, &mut self.problem, &self.options)?;
        self.summary = Some(summary);
        Ok(self.values())
    }

    fn values(&self) -> Values {
        values_of(&self.problem)
    }
}

/// Runs the library's solver without the GIL: other Python threads run meanwhile, and a
/// `CustomFactor`'s error function can take it from whichever thread evaluates it.
fn solve_detached(
    py: Python<'_>,
    problem: &mut Problem,
    options: &SolverOptions,
) -> PyResult<Summary> {
    py.detach(|| {
        solver::optimize(problem, options, &mut |_| {
            std::ops::ControlFlow::Continue(())
        })
    })
    .map_err(solver_error)
}

/// The problem's current values as a `Values`.
pub fn values_of(problem: &Problem) -> Values {
    let v = &problem.values;
    Values {
        map: (0..v.len())
            .map(|i| (v.key(i), v.variable(i).clone_box()))
            .collect(),
    }
}

/// The Summary as a Python dict (through its JSON form, the one the server sends).
pub fn summary_dict(py: Python<'_>, summary: &Summary) -> PyResult<Py<PyAny>> {
    static LOADS: pyo3::sync::PyOnceLock<Py<PyAny>> = pyo3::sync::PyOnceLock::new();
    let json = serde_json::to_string(summary)
        .map_err(|e| FactordError::new_err(format!("summary: {e}")))?;
    let loads = LOADS.get_or_try_init(py, || {
        py.import("json")?.getattr("loads").map(Bound::unbind)
    })?;
    Ok(loads.bind(py).call1((json,))?.unbind())
}

/// An optimizer class: constructor, `optimize`, `values`, `error`, `iterations`, `summary`.
macro_rules! optimizer_class {
    ($name:ident, $method:expr) => {
        #[pyclass(module = "factord", unsendable)]
        pub struct $name {
            inner: Optimizer,
        }

        #[pymethods]
        impl $name {
            #[new]
            #[pyo3(signature = (graph, initial, params = None))]
            fn new(
                graph: &NonlinearFactorGraph,
                initial: &Values,
                params: Option<PyRef<'_, OptimizerParams>>,
            ) -> PyResult<Self> {
                Ok(Self {
                    inner: Optimizer::new(graph, initial, params.as_deref(), $method)?,
                })
            }
            /// Runs to convergence (or the iteration limit) and returns the estimate.
            fn optimize(&mut self, py: Python<'_>) -> PyResult<Values> {
                self.inner.optimize(py)
            }
            /// The current estimate.
            fn values(&self) -> Values {
                self.inner.values()
            }
            /// `½ Σ ρ` at the current estimate.
            fn error(&self) -> PyResult<f64> {
                Ok(0.5 * crate::errors::chi2_of(&self.inner.problem)?)
            }
            fn iterations(&self) -> usize {
                self.inner.summary.as_ref().map_or(0, |s| s.iterations)
            }
            /// The last solve's Summary as a dict (`None` before `optimize`); factord's own.
            fn summary(&self, py: Python<'_>) -> PyResult<Py<PyAny>> {
                match &self.inner.summary {
                    Some(s) => summary_dict(py, s),
                    None => Ok(py.None()),
                }
            }
        }
    };
}
optimizer_class!(LevenbergMarquardtOptimizer, Method::LevenbergMarquardt);
optimizer_class!(GaussNewtonOptimizer, Method::GaussNewton);
optimizer_class!(DoglegOptimizer, Method::Dogleg);

/// factord's own call: `solve(graph, initial, method="lm", max_iterations=100, ...)` returns
/// `(values, summary)` with the library's defaults (tolerances, chordal initialisation on `auto`).
#[pyfunction]
#[pyo3(signature = (graph, initial, method = "levenberg_marquardt", max_iterations = None, function_tolerance = None, initialization = "none"))]
pub fn solve(
    py: Python<'_>,
    graph: &NonlinearFactorGraph,
    initial: &Values,
    method: &str,
    max_iterations: Option<usize>,
    function_tolerance: Option<f64>,
    initialization: &str,
) -> PyResult<(Values, Py<PyAny>)> {
    let method = Method::parse(method).ok_or_else(|| {
        FactordError::new_err(format!(
            "method {method:?}: expected gauss_newton (gn), levenberg_marquardt (lm) or dogleg"
        ))
    })?;
    let initialization = match initialization {
        "none" => Initialization::None,
        "chordal" => Initialization::Chordal,
        "auto" => Initialization::Auto,
        other => {
            return Err(FactordError::new_err(format!(
                "initialization {other:?}: expected none, chordal or auto"
            )))
        }
    };
    let defaults = SolverOptions::default();
    let options = SolverOptions {
        method,
        max_iterations: max_iterations.unwrap_or(defaults.max_iterations),
        function_tolerance: function_tolerance.unwrap_or(defaults.function_tolerance),
        initialization,
        ..defaults
    };
    options
        .validate()
        .map_err(|(field, why)| FactordError::new_err(format!("{field}: {why}")))?;
    let mut problem = build_problem(initial, graph.present())?;
    // As `factord solve`: a component without a prior is anchored at its lowest key.
    problem.gauge = factord::problem::Gauge::AnchorComponents;
    let summary = solve_detached(py, &mut problem, &options)?;
    Ok((values_of(&problem), summary_dict(py, &summary)?))
}
