//! `Marginals(graph, values)`: covariances from one factorisation of the Hessian at `values`,
//! given in GTSAM's tangent conventions: a `Pose2`'s in its body frame (x, y, θ), a `Pose3`'s
//! rotation first. The library's own are a `Pose2`'s world-frame increments and a `Pose3`'s
//! translation first; each block is mapped with the first-order change of coordinates.

use nalgebra::DMatrix;
use pyo3::prelude::*;

use factord::problem::{Key, Problem};
use factord::solver::marginals::{Covariance, Marginals as LibraryMarginals, MarginalsError};

use crate::arrays::dmatrix_out;
use crate::errors::{solver_error, FactordError, ValuesKeyDoesNotExist};
use crate::graph::{build_problem, NonlinearFactorGraph};
use crate::keys::key_name;
use crate::values::Values;

#[pyclass(module = "factord", name = "Marginals", unsendable)]
pub struct Marginals {
    problem: Problem,
    inner: LibraryMarginals,
}

/// The matrix taking the library tangent of `key`'s variable to GTSAM's.
fn to_gtsam_tangent(problem: &Problem, key: Key) -> DMatrix<f64> {
    crate::values::to_gtsam_tangent(
        problem
            .values
            .get(key)
            .expect("asked keys are in the problem"),
    )
}

pub fn marginals_error(e: MarginalsError) -> PyErr {
    match e {
        MarginalsError::UnknownVariable { key } => {
            ValuesKeyDoesNotExist::new_err(format!("Marginals: no variable {}", key_name(key)))
        }
        MarginalsError::Repeated { key } => {
            FactordError::new_err(format!("Marginals: variable {} asked twice", key_name(key)))
        }
    }
}

impl Marginals {
    /// `marginalCovariance` for other classes of this crate.
    pub fn marginal_covariance_of<'py>(
        &self,
        py: Python<'py>,
        key: Key,
    ) -> PyResult<Bound<'py, PyAny>> {
        dmatrix_out(py, &self.joint(&[key])?.0)
    }

    pub fn of_problem(problem: Problem) -> PyResult<Self> {
        let inner = LibraryMarginals::new(&problem).map_err(solver_error)?;
        Ok(Self { problem, inner })
    }

    /// The joint covariance of `keys` in GTSAM's conventions, with each key's dimension.
    fn joint(&self, keys: &[Key]) -> PyResult<(DMatrix<f64>, Vec<usize>)> {
        let Covariance { dims, joint, .. } =
            self.inner.covariance(keys).map_err(marginals_error)?;
        let n: usize = dims.iter().sum();
        let sigma = DMatrix::from_row_slice(n, n, &joint);
        let mut t = DMatrix::zeros(n, n);
        let mut at = 0;
        for (&k, &d) in keys.iter().zip(&dims) {
            t.view_mut((at, at), (d, d))
                .copy_from(&to_gtsam_tangent(&self.problem, k));
            at += d;
        }
        Ok((&t * sigma * t.transpose(), dims))
    }
}

#[pymethods]
impl Marginals {
    #[new]
    fn new(graph: &NonlinearFactorGraph, values: &Values) -> PyResult<Self> {
        Self::of_problem(build_problem(values, graph.present())?)
    }
    #[pyo3(name = "marginalCovariance")]
    fn marginal_covariance<'py>(&self, py: Python<'py>, key: Key) -> PyResult<Bound<'py, PyAny>> {
        dmatrix_out(py, &self.joint(&[key])?.0)
    }
    #[pyo3(name = "marginalInformation")]
    fn marginal_information<'py>(&self, py: Python<'py>, key: Key) -> PyResult<Bound<'py, PyAny>> {
        let c = self.joint(&[key])?.0;
        let i = c.try_inverse().ok_or_else(|| {
            FactordError::new_err(format!(
                "the covariance of {} is singular (a fixed variable?)",
                key_name(key)
            ))
        })?;
        dmatrix_out(py, &i)
    }
    #[pyo3(name = "jointMarginalCovariance")]
    fn joint_marginal_covariance(&self, keys: Vec<Key>) -> PyResult<JointMarginal> {
        let (matrix, dims) = self.joint(&keys)?;
        Ok(JointMarginal { keys, dims, matrix })
    }
}

/// A joint covariance with its blocks addressed by key (GTSAM: `JointMarginal`).
#[pyclass(module = "factord", name = "JointMarginal")]
pub struct JointMarginal {
    keys: Vec<Key>,
    dims: Vec<usize>,
    matrix: DMatrix<f64>,
}

#[pymethods]
impl JointMarginal {
    /// The block between `key1` and `key2`.
    fn at<'py>(&self, py: Python<'py>, key1: Key, key2: Key) -> PyResult<Bound<'py, PyAny>> {
        let place = |key: Key| -> PyResult<(usize, usize)> {
            let i = self.keys.iter().position(|&k| k == key).ok_or_else(|| {
                ValuesKeyDoesNotExist::new_err(format!(
                    "JointMarginal has no variable {}",
                    key_name(key)
                ))
            })?;
            Ok((self.dims[..i].iter().sum(), self.dims[i]))
        };
        let (r, dr) = place(key1)?;
        let (c, dc) = place(key2)?;
        dmatrix_out(py, &self.matrix.view((r, c), (dr, dc)).into_owned())
    }
    #[pyo3(name = "fullMatrix")]
    fn full_matrix<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        dmatrix_out(py, &self.matrix)
    }
    fn keys(&self) -> Vec<Key> {
        self.keys.clone()
    }
}
