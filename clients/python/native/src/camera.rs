//! `SnavelyCamera`: the camera of the BAL datasets (Bundler's model) as a Python value, and the
//! factor that sees a 3D point through it. factord's own names: GTSAM's BAL classes
//! (`PinholeCameraCal3Bundler`, `GeneralSFMFactorCal3Bundler`) put the camera in another frame
//! (looking down +z, its pose camera-to-world), so a GTSAM script's numbers would not carry over.
//!
//! ```text
//! P = R X + t,   p = −(P.x, P.y) / P.z,   uv = f (1 + k1 ‖p‖² + k2 ‖p‖⁴) p
//! ```

use nalgebra::{Vector2, Vector3};
use pyo3::prelude::*;

use factord::geometry::SnavelyCamera as LibraryCamera;

use crate::arrays::{fixed_vector_in, vector_out};
use crate::spatial::Rot3;

#[pyclass(module = "factord", name = "SnavelyCamera", from_py_object)]
#[derive(Clone, Copy, Debug)]
pub struct SnavelyCamera {
    pub inner: LibraryCamera,
}

#[pymethods]
impl SnavelyCamera {
    /// `SnavelyCamera(rotation, translation, focal, k1=0, k2=0)`: world → camera `R X + t`.
    #[new]
    #[pyo3(signature = (rotation, translation, focal, k1 = 0.0, k2 = 0.0))]
    fn new(
        rotation: &Rot3,
        translation: &Bound<'_, PyAny>,
        focal: f64,
        k1: f64,
        k2: f64,
    ) -> PyResult<Self> {
        let t = fixed_vector_in(translation, 3, "SnavelyCamera translation")?;
        Ok(Self {
            inner: LibraryCamera {
                rotation: rotation.inner,
                translation: Vector3::new(t[0], t[1], t[2]),
                focal,
                k1,
                k2,
            },
        })
    }
    /// From BAL's nine numbers: angle-axis (3), translation (3), f, k1, k2.
    #[staticmethod]
    #[pyo3(name = "fromBal")]
    fn from_bal(parameters: &Bound<'_, PyAny>) -> PyResult<Self> {
        let p = fixed_vector_in(parameters, 9, "SnavelyCamera.fromBal")?;
        let mut nine = [0.0; 9];
        nine.copy_from_slice(&p);
        Ok(Self {
            inner: LibraryCamera::from_bal(&nine),
        })
    }
    /// BAL's nine numbers.
    fn bal<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        vector_out(py, &self.inner.to_bal())
    }
    fn rotation(&self) -> Rot3 {
        Rot3 {
            inner: self.inner.rotation,
        }
    }
    fn translation<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        vector_out(py, self.inner.translation.as_slice())
    }
    fn focal(&self) -> f64 {
        self.inner.focal
    }
    fn k1(&self) -> f64 {
        self.inner.k1
    }
    fn k2(&self) -> f64 {
        self.inner.k2
    }
    /// The pixel at which a world point is seen.
    fn project<'py>(
        &self,
        py: Python<'py>,
        point: &Bound<'_, PyAny>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let x = fixed_vector_in(point, 3, "SnavelyCamera.project: point")?;
        let uv: Vector2<f64> = self.inner.project(&Vector3::new(x[0], x[1], x[2]));
        vector_out(py, uv.as_slice())
    }
    /// The camera centre in the world, `−Rᵀ t`.
    fn centre<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        vector_out(py, self.inner.centre().as_slice())
    }
    fn equals(&self, other: &SnavelyCamera, tol: f64) -> bool {
        let (a, b) = (self.inner.to_bal(), other.inner.to_bal());
        a.iter().zip(&b).all(|(x, y)| (x - y).abs() <= tol)
    }
    fn __repr__(&self) -> String {
        let b = self.inner.to_bal();
        format!(
            "SnavelyCamera(angle-axis [{:.6}, {:.6}, {:.6}], t [{:.6}, {:.6}, {:.6}], f {:.6}, k1 {:.6}, k2 {:.6})",
            b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7], b[8]
        )
    }
}
