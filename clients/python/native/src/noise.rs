//! Noise models as GTSAM builds them (`Diagonal.Sigmas`, `Isotropic.Sigma`, `Gaussian.Covariance`,
//! `Robust.Create(mEstimator.Huber.Create(k), base)`, ...). A model keeps its information matrix in
//! the order of GTSAM's tangent (for `Pose3`: rotation first); the factor that uses it reorders it
//! to the library's residual once (`factors.rs`). The Python namespaces (`noiseModel.Diagonal`,
//! ...) are in `python/factord/__init__.py` over the constructors here.

use nalgebra::{DMatrix, DVector};
use pyo3::prelude::*;

use factord::factors::robust::scale_in_range;
use factord::factors::RobustKernel;

use crate::arrays::{dmatrix_out, matrix_in, vector_in, vector_out};
use crate::errors::{DimensionMismatch, InvalidNoiseModel};

/// A robust kernel (GTSAM: `noiseModel.mEstimator.Huber.Create(k)` and kin).
#[pyclass(module = "factord", name = "MEstimator", from_py_object)]
#[derive(Clone, Copy, Debug)]
pub struct MEstimator {
    pub kernel: RobustKernel,
}

#[pymethods]
impl MEstimator {
    /// `kind` is `huber`, `cauchy`, `tukey` or `geman_mcclure`; `k` the threshold in whitened units.
    #[new]
    fn new(kind: &str, k: f64) -> PyResult<Self> {
        if !scale_in_range(k) {
            return Err(InvalidNoiseModel::new_err(format!(
                "mEstimator {kind}: threshold {k} is not between 1e-9 and 1e9"
            )));
        }
        let kernel = match kind {
            "huber" => RobustKernel::Huber(k),
            "cauchy" => RobustKernel::Cauchy(k),
            "tukey" => RobustKernel::Tukey(k),
            "geman_mcclure" => RobustKernel::GemanMcclure(k),
            other => {
                return Err(InvalidNoiseModel::new_err(format!(
                    "unknown mEstimator {other} (huber, cauchy, tukey or geman_mcclure)"
                )))
            }
        };
        Ok(Self { kernel })
    }
    fn __repr__(&self) -> String {
        format!("MEstimator({:?})", self.kernel)
    }
}

/// A Gaussian noise model, possibly robust.
#[pyclass(module = "factord", name = "NoiseModel", from_py_object)]
#[derive(Clone, Debug)]
pub struct NoiseModel {
    /// In GTSAM's tangent order.
    pub information: DMatrix<f64>,
    pub robust: Option<RobustKernel>,
    /// `Diagonal`, `Isotropic`, `Unit`, `Gaussian` (for printing).
    pub family: &'static str,
}

fn positive_finite(values: &[f64], what: &str) -> PyResult<()> {
    match values.iter().find(|v| !(v.is_finite() && **v > 0.0)) {
        Some(bad) => Err(InvalidNoiseModel::new_err(format!(
            "{what} must be finite and > 0, got {bad}"
        ))),
        None => Ok(()),
    }
}

/// The largest noise model dimension: far above any factor's residual, and small enough that its
/// matrix (dimension² doubles) is always allocated (10¹² would abort the process).
const MAX_DIM: usize = 1000;

fn positive_dim(dim: usize, what: &str) -> PyResult<()> {
    if dim == 0 || dim > MAX_DIM {
        return Err(DimensionMismatch::new_err(format!(
            "{what}: dimension must be from 1 to {MAX_DIM}, got {dim}"
        )));
    }
    Ok(())
}

impl NoiseModel {
    fn diagonal_information(precisions: Vec<f64>, family: &'static str) -> Self {
        Self {
            information: DMatrix::from_diagonal(&DVector::from_vec(precisions)),
            robust: None,
            family,
        }
    }

    pub fn size(&self) -> usize {
        self.information.nrows()
    }

    /// The information matrix checked positive definite (Cholesky).
    fn checked(information: DMatrix<f64>, what: &str) -> PyResult<Self> {
        if information.iter().any(|v| !v.is_finite()) || information.clone().cholesky().is_none() {
            return Err(InvalidNoiseModel::new_err(format!(
                "{what}: not a positive definite matrix"
            )));
        }
        Ok(Self {
            information,
            robust: None,
            family: "Gaussian",
        })
    }
}

#[pymethods]
impl NoiseModel {
    #[staticmethod]
    fn diagonal_sigmas(sigmas: &Bound<'_, PyAny>) -> PyResult<Self> {
        let s = vector_in(sigmas, "Diagonal.Sigmas")?;
        positive_dim(s.len(), "Diagonal.Sigmas")?;
        positive_finite(&s, "Diagonal.Sigmas: every sigma")?;
        Ok(Self::diagonal_information(
            s.iter().map(|v| 1.0 / (v * v)).collect(),
            "Diagonal",
        ))
    }
    #[staticmethod]
    fn diagonal_variances(variances: &Bound<'_, PyAny>) -> PyResult<Self> {
        let v = vector_in(variances, "Diagonal.Variances")?;
        positive_dim(v.len(), "Diagonal.Variances")?;
        positive_finite(&v, "Diagonal.Variances: every variance")?;
        Ok(Self::diagonal_information(
            v.iter().map(|v| 1.0 / v).collect(),
            "Diagonal",
        ))
    }
    #[staticmethod]
    fn diagonal_precisions(precisions: &Bound<'_, PyAny>) -> PyResult<Self> {
        let p = vector_in(precisions, "Diagonal.Precisions")?;
        positive_dim(p.len(), "Diagonal.Precisions")?;
        positive_finite(&p, "Diagonal.Precisions: every precision")?;
        Ok(Self::diagonal_information(p, "Diagonal"))
    }
    #[staticmethod]
    fn isotropic_sigma(dim: usize, sigma: f64) -> PyResult<Self> {
        positive_dim(dim, "Isotropic.Sigma")?;
        positive_finite(&[sigma], "Isotropic.Sigma: sigma")?;
        Ok(Self::diagonal_information(
            vec![1.0 / (sigma * sigma); dim],
            "Isotropic",
        ))
    }
    #[staticmethod]
    fn isotropic_variance(dim: usize, variance: f64) -> PyResult<Self> {
        positive_dim(dim, "Isotropic.Variance")?;
        positive_finite(&[variance], "Isotropic.Variance: variance")?;
        Ok(Self::diagonal_information(
            vec![1.0 / variance; dim],
            "Isotropic",
        ))
    }
    #[staticmethod]
    fn isotropic_precision(dim: usize, precision: f64) -> PyResult<Self> {
        positive_dim(dim, "Isotropic.Precision")?;
        positive_finite(&[precision], "Isotropic.Precision: precision")?;
        Ok(Self::diagonal_information(
            vec![precision; dim],
            "Isotropic",
        ))
    }
    #[staticmethod]
    fn unit(dim: usize) -> PyResult<Self> {
        positive_dim(dim, "Unit.Create")?;
        Ok(Self::diagonal_information(vec![1.0; dim], "Unit"))
    }
    #[staticmethod]
    fn gaussian_covariance(covariance: &Bound<'_, PyAny>) -> PyResult<Self> {
        let c = matrix_in(covariance, None, None, "Gaussian.Covariance")?;
        positive_dim(c.nrows(), "Gaussian.Covariance")?;
        let inverse = c
            .clone()
            .cholesky()
            .filter(|_| c.iter().all(|v| v.is_finite()))
            .map(|ch| ch.inverse())
            .ok_or_else(|| {
                InvalidNoiseModel::new_err("Gaussian.Covariance: not a positive definite matrix")
            })?;
        Self::checked(inverse, "Gaussian.Covariance")
    }
    #[staticmethod]
    fn gaussian_information(information: &Bound<'_, PyAny>) -> PyResult<Self> {
        let i = matrix_in(information, None, None, "Gaussian.Information")?;
        positive_dim(i.nrows(), "Gaussian.Information")?;
        Self::checked(i, "Gaussian.Information")
    }
    /// From `R` with `Ω = Rᵀ R` (GTSAM: `Gaussian.SqrtInformation`).
    #[staticmethod]
    fn gaussian_sqrt_information(r: &Bound<'_, PyAny>) -> PyResult<Self> {
        let r = matrix_in(r, None, None, "Gaussian.SqrtInformation")?;
        positive_dim(r.nrows(), "Gaussian.SqrtInformation")?;
        Self::checked(r.transpose() * &r, "Gaussian.SqrtInformation")
    }
    /// `Robust.Create(mEstimator, base)`.
    #[staticmethod]
    fn robust(m_estimator: &MEstimator, base: &NoiseModel) -> PyResult<Self> {
        if base.robust.is_some() {
            return Err(InvalidNoiseModel::new_err(
                "Robust.Create: the base noise model is robust already",
            ));
        }
        Ok(Self {
            robust: Some(m_estimator.kernel),
            ..base.clone()
        })
    }
    fn dim(&self) -> usize {
        self.size()
    }
    #[pyo3(name = "isRobust")]
    fn is_robust(&self) -> bool {
        self.robust.is_some()
    }
    /// Σ (GTSAM's tangent order).
    fn covariance<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let c = self
            .information
            .clone()
            .try_inverse()
            .ok_or_else(|| InvalidNoiseModel::new_err("the information is not invertible"))?;
        dmatrix_out(py, &c)
    }
    fn information<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        dmatrix_out(py, &self.information)
    }
    /// The standard deviations along the axes (of a diagonal model; the marginal ones otherwise).
    fn sigmas<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let c = self
            .information
            .clone()
            .try_inverse()
            .ok_or_else(|| InvalidNoiseModel::new_err("the information is not invertible"))?;
        let s: Vec<f64> = (0..c.nrows()).map(|i| c[(i, i)].sqrt()).collect();
        vector_out(py, &s)
    }
    fn __repr__(&self) -> String {
        match self.robust {
            Some(k) => format!(
                "noiseModel.Robust({:?}, {} dim {})",
                k,
                self.family,
                self.size()
            ),
            None => format!("noiseModel.{} dim {}", self.family, self.size()),
        }
    }
}
