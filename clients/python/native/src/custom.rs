//! `CustomFactor(noise, keys, error_func)`: a factor whose error (and Jacobians) a Python
//! function computes, with GTSAM's call shape:
//!
//! ```python
//! def error_func(this: CustomFactor, v: Values, H: Optional[List[np.ndarray]]) -> np.ndarray:
//!     ...  # the unwhitened error; when H is a list, set H[i] to ∂error/∂ξ_i
//! ```
//!
//! The Jacobians are given in GTSAM's tangent conventions (a `Pose2`'s body-frame (x, y, θ), a
//! `Pose3`'s rotation first, points additive); the library's own tangent is converted here, so
//! the solver sees the Jacobian of its own retraction: `J_library = J_gtsam · ∂ξ_gtsam/∂δ`.
//!
//! The function runs inside the library's solvers, on whichever thread evaluates the factor;
//! every solve of this crate releases the GIL (`py.detach`), so a second thread of an iSAM2
//! update can take it. An exception the function raises stops the solve and is raised again
//! from the call that started it (`take_raised`), unchanged.

use std::sync::{Arc, Mutex, OnceLock};

use nalgebra::DMatrix;
use pyo3::prelude::*;
use pyo3::types::PyList;

use factord::factors::{EvaluationError, Factor};
use factord::problem::{Key, Problem};
use factord::variables::Variable;

use crate::arrays::{matrix_in, vector_in};
use crate::errors::ValuesKeyDoesNotExist;
use crate::factors::{FactorClass, FactorData, NonlinearFactor};
use crate::keys::key_name;
use crate::noise::NoiseModel;
use crate::values::{to_gtsam_tangent, Values};

/// The first exception a Python error function raised since it was last taken.
static RAISED: Mutex<Option<PyErr>> = Mutex::new(None);

/// The exception a Python error function raised during the last failed call, if one did.
pub fn take_raised() -> Option<PyErr> {
    RAISED.lock().unwrap_or_else(|p| p.into_inner()).take()
}

fn keep_raised(e: PyErr) {
    let mut slot = RAISED.lock().unwrap_or_else(|p| p.into_inner());
    if slot.is_none() {
        *slot = Some(e);
    }
}

/// The library factor: keys, the error's dimension, the Python function, and the noise model
/// (to hand `this` to the function as a `CustomFactor` of its own). The kinds of its variables
/// are unknown until it meets values: a graph's factor has none, and each problem gets a copy
/// naming the kinds of the values it was added with ([`with_kinds`]).
#[derive(Debug)]
pub struct PythonFactor {
    keys: Vec<Key>,
    kinds: Vec<&'static str>,
    dim: usize,
    function: Py<PyAny>,
    noise: NoiseModel,
    label: String,
    /// The function's `this`, made at the first call (a `CustomFactor` over a copy of this
    /// factor, so it does not hold the object that holds this one: no cycle).
    this: OnceLock<Py<PyAny>>,
}

impl PythonFactor {
    fn failed(&self, message: impl Into<String>) -> EvaluationError {
        EvaluationError::Failed {
            factor: self.label.clone(),
            message: message.into(),
        }
    }

    /// Calls the function; the error and, when asked, the Jacobians (GTSAM's tangents).
    fn call(
        &self,
        py: Python<'_>,
        variables: &[&dyn Variable],
        with_jacobians: bool,
    ) -> PyResult<(Vec<f64>, Option<Vec<DMatrix<f64>>>)> {
        let mut values = Values::default();
        for (&k, v) in self.keys.iter().zip(variables) {
            values.map.insert(k, v.clone_box());
        }
        let this = self.this(py)?;
        let h = if with_jacobians {
            Some(PyList::new(py, self.keys.iter().map(|_| py.None()))?)
        } else {
            None
        };
        let returned = self.function.bind(py).call1((this, values, h.clone()))?;
        let error = vector_in(
            &returned,
            &format!("{}: the error function's result", self.label),
        )?;
        let Some(h) = h else {
            return Ok((error, None));
        };
        let mut jacobians = Vec::with_capacity(self.keys.len());
        for (i, v) in variables.iter().enumerate() {
            let item = h.get_item(i)?;
            if item.is_none() {
                return Err(crate::errors::FactordError::new_err(format!(
                    "{}: the error function was asked for Jacobians and left H[{i}] unset",
                    self.label
                )));
            }
            jacobians.push(matrix_in(
                &item,
                Some(self.dim),
                Some(v.tangent_dim()),
                &format!("{}: H[{i}]", self.label),
            )?);
        }
        Ok((error, Some(jacobians)))
    }

    /// The same factor, naming `kinds`.
    fn with(&self, py: Python<'_>, kinds: Vec<&'static str>) -> PythonFactor {
        PythonFactor {
            keys: self.keys.clone(),
            kinds,
            dim: self.dim,
            function: self.function.clone_ref(py),
            noise: self.noise.clone(),
            label: self.label.clone(),
            this: OnceLock::new(),
        }
    }

    /// The function's `this`: a `CustomFactor` object for this factor, made once.
    fn this(&self, py: Python<'_>) -> PyResult<Py<PyAny>> {
        if let Some(this) = self.this.get() {
            return Ok(this.clone_ref(py));
        }
        let copy = self.with(py, self.kinds.clone());
        let data = FactorData::new(Box::new(copy), &self.noise, FactorClass::CustomFactor, None)?;
        let base = NonlinearFactor {
            data: Arc::new(data),
        };
        let this = Py::new(
            py,
            PyClassInitializer::from(base).add_subclass(CustomFactor),
        )?
        .into_any();
        Ok(self.this.get_or_init(|| this).clone_ref(py))
    }
}

impl Factor for PythonFactor {
    fn name(&self) -> &str {
        "python"
    }
    fn keys(&self) -> &[Key] {
        &self.keys
    }
    fn residual_dim(&self) -> usize {
        self.dim
    }
    fn variable_kinds(&self) -> &[&'static str] {
        &self.kinds
    }
    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let with_jacobians = jacobian.is_some();
        let called = Python::attach(|py| {
            self.call(py, variables, with_jacobians).map_err(|e| {
                let message = e.to_string();
                keep_raised(e);
                self.failed(message)
            })
        });
        let (values, jacobians) = called?;
        if values.len() != self.dim {
            let message = format!(
                "the error function returned {} numbers, the noise model has dimension {}",
                values.len(),
                self.dim
            );
            keep_raised(crate::errors::DimensionMismatch::new_err(format!(
                "{}: {message}",
                self.label
            )));
            return Err(self.failed(message));
        }
        error.copy_from_slice(&values);
        if let (Some(out), Some(jacobians)) = (jacobian, jacobians) {
            let cols: usize = variables.iter().map(|v| v.tangent_dim()).sum();
            let mut at = 0;
            for (v, j) in variables.iter().zip(&jacobians) {
                let library = j * to_gtsam_tangent(*v);
                for r in 0..self.dim {
                    for c in 0..library.ncols() {
                        out[r * cols + at + c] = library[(r, c)];
                    }
                }
                at += library.ncols();
            }
        }
        Ok(())
    }
    fn as_any(&self) -> &dyn std::any::Any {
        self
    }
}

/// The factor to add to `problem` for `data`: a Python factor with the kinds of the problem's
/// values at its keys (every key must have one), any other factor as it is.
pub fn with_kinds(problem: &Problem, data: &FactorData) -> PyResult<Option<Box<dyn Factor>>> {
    let Some(factor) = data.factor.as_any().downcast_ref::<PythonFactor>() else {
        return Ok(None);
    };
    let kinds = factor
        .keys
        .iter()
        .map(|&k| {
            problem.values.get(k).map(|v| v.kind()).ok_or_else(|| {
                ValuesKeyDoesNotExist::new_err(format!(
                    "{}: no initial value for variable {}",
                    data.label,
                    key_name(k)
                ))
            })
        })
        .collect::<PyResult<Vec<_>>>()?;
    Ok(Some(Box::new(Python::attach(|py| factor.with(py, kinds)))))
}

/// GTSAM's `CustomFactor(noiseModel, keys, errorFunction)`.
#[pyclass(module = "factord", extends = NonlinearFactor)]
pub struct CustomFactor;

#[pymethods]
impl CustomFactor {
    #[new]
    #[pyo3(signature = (noise, keys, error_func))]
    fn new(
        noise: &NoiseModel,
        keys: Vec<Key>,
        error_func: Bound<'_, PyAny>,
    ) -> PyResult<PyClassInitializer<Self>> {
        if !error_func.is_callable() {
            return Err(pyo3::exceptions::PyTypeError::new_err(
                "CustomFactor: error_func must be callable (this, values, H) -> error",
            ));
        }
        if keys.is_empty() {
            return Err(crate::errors::FactordError::new_err(
                "CustomFactor: at least one key is needed",
            ));
        }
        let names: Vec<String> = keys.iter().map(|&k| key_name(k)).collect();
        let factor = PythonFactor {
            keys,
            kinds: Vec::new(),
            dim: noise.size(),
            function: error_func.unbind(),
            noise: noise.clone(),
            label: format!("CustomFactor({})", names.join(", ")),
            this: OnceLock::new(),
        };
        let data = FactorData::new(Box::new(factor), noise, FactorClass::CustomFactor, None)?;
        Ok(PyClassInitializer::from(NonlinearFactor {
            data: Arc::new(data),
        })
        .add_subclass(CustomFactor))
    }
}
