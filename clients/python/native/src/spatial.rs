//! `Rot3` and `Pose3` with GTSAM's constructors and methods, over the library's `Se3`. Tangent
//! vectors of `Pose3` (`Expmap`, `Logmap`) are in GTSAM's order, rotation first.

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3, Vector6};
use pyo3::prelude::*;

use factord::geometry::{so3, Se3};

use crate::arrays::{fixed_vector_in, matrix_in, matrix_out, vector_out};

#[pyclass(module = "factord", name = "Rot3", from_py_object)]
#[derive(Clone, Copy, Debug)]
pub struct Rot3 {
    pub inner: UnitQuaternion<f64>,
}

fn rot3_of_matrix(m: &nalgebra::DMatrix<f64>) -> UnitQuaternion<f64> {
    let m3 = Matrix3::from_fn(|r, c| m[(r, c)]);
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&m3))
}

#[pymethods]
impl Rot3 {
    /// `Rot3()` or `Rot3(3×3 matrix)`.
    #[new]
    #[pyo3(signature = (matrix = None))]
    fn new(matrix: Option<&Bound<'_, PyAny>>) -> PyResult<Self> {
        Ok(Self {
            inner: match matrix {
                None => UnitQuaternion::identity(),
                Some(m) => rot3_of_matrix(&matrix_in(m, Some(3), Some(3), "Rot3(matrix)")?),
            },
        })
    }
    /// From a quaternion `w, x, y, z` (normalised).
    #[staticmethod]
    #[pyo3(name = "Quaternion")]
    fn quaternion_ctor(w: f64, x: f64, y: f64, z: f64) -> Self {
        Self {
            inner: UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z)),
        }
    }
    #[staticmethod]
    #[pyo3(name = "Rx")]
    fn rx(angle: f64) -> Self {
        Self::from_axis(Vector3::x_axis(), angle)
    }
    #[staticmethod]
    #[pyo3(name = "Ry")]
    fn ry(angle: f64) -> Self {
        Self::from_axis(Vector3::y_axis(), angle)
    }
    #[staticmethod]
    #[pyo3(name = "Rz")]
    fn rz(angle: f64) -> Self {
        Self::from_axis(Vector3::z_axis(), angle)
    }
    /// `Rz(yaw) Ry(pitch) Rx(roll)`.
    #[staticmethod]
    #[pyo3(name = "Ypr")]
    fn ypr_ctor(yaw: f64, pitch: f64, roll: f64) -> Self {
        Self {
            inner: UnitQuaternion::from_euler_angles(roll, pitch, yaw),
        }
    }
    #[staticmethod]
    #[pyo3(name = "RzRyRx")]
    fn rz_ry_rx(x: f64, y: f64, z: f64) -> Self {
        Self::ypr_ctor(z, y, x)
    }
    #[staticmethod]
    #[pyo3(name = "Expmap")]
    fn expmap(v: &Bound<'_, PyAny>) -> PyResult<Self> {
        let v = fixed_vector_in(v, 3, "Rot3.Expmap")?;
        Ok(Self {
            inner: so3::exp(&Vector3::new(v[0], v[1], v[2])),
        })
    }
    #[staticmethod]
    #[pyo3(name = "Logmap")]
    fn logmap<'py>(py: Python<'py>, r: &Rot3) -> PyResult<Bound<'py, PyAny>> {
        vector_out(py, so3::log(&r.inner).as_slice())
    }
    fn matrix<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let m = self.inner.to_rotation_matrix().into_inner();
        let row_major: Vec<f64> = (0..9).map(|k| m[(k / 3, k % 3)]).collect();
        matrix_out(py, 3, 3, &row_major)
    }
    /// `[w, x, y, z]`.
    fn quaternion<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let q = self.inner.quaternion();
        vector_out(py, &[q.w, q.i, q.j, q.k])
    }
    /// `[yaw, pitch, roll]`.
    fn ypr<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let (r, p, y) = self.inner.euler_angles();
        vector_out(py, &[y, p, r])
    }
    /// `[roll, pitch, yaw]`.
    fn rpy<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let (r, p, y) = self.inner.euler_angles();
        vector_out(py, &[r, p, y])
    }
    fn roll(&self) -> f64 {
        self.inner.euler_angles().0
    }
    fn pitch(&self) -> f64 {
        self.inner.euler_angles().1
    }
    fn yaw(&self) -> f64 {
        self.inner.euler_angles().2
    }
    fn inverse(&self) -> Self {
        Self {
            inner: self.inner.inverse(),
        }
    }
    fn compose(&self, other: &Rot3) -> Self {
        Self {
            inner: self.inner * other.inner,
        }
    }
    fn __mul__(&self, other: &Rot3) -> Self {
        self.compose(other)
    }
    fn between(&self, other: &Rot3) -> Self {
        Self {
            inner: self.inner.inverse() * other.inner,
        }
    }
    fn rotate<'py>(&self, py: Python<'py>, p: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyAny>> {
        let p = fixed_vector_in(p, 3, "Rot3.rotate: point")?;
        vector_out(py, (self.inner * Vector3::new(p[0], p[1], p[2])).as_slice())
    }
    fn unrotate<'py>(&self, py: Python<'py>, p: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyAny>> {
        self.inverse().rotate(py, p)
    }
    #[pyo3(signature = (other, tol = 1e-9))]
    fn equals(&self, other: &Rot3, tol: f64) -> bool {
        so3::log(&(self.inner.inverse() * other.inner)).amax() <= tol
    }
    fn __repr__(&self) -> String {
        let q = self.inner.quaternion();
        format!("Rot3.Quaternion({}, {}, {}, {})", q.w, q.i, q.j, q.k)
    }
}

impl Rot3 {
    fn from_axis(axis: nalgebra::Unit<Vector3<f64>>, angle: f64) -> Self {
        Self {
            inner: UnitQuaternion::from_axis_angle(&axis, angle),
        }
    }
}

#[pyclass(module = "factord", name = "Pose3", from_py_object)]
#[derive(Clone, Copy, Debug)]
pub struct Pose3 {
    pub inner: Se3,
}

impl Pose3 {
    pub fn from_se3(inner: Se3) -> Self {
        Self { inner }
    }
}

/// GTSAM's tangent `(ω, v)` as the library's `(v, ω)`, and back (the swap is its own inverse).
fn swap_halves(v: &[f64]) -> Vector6<f64> {
    Vector6::new(v[3], v[4], v[5], v[0], v[1], v[2])
}

#[pymethods]
impl Pose3 {
    /// `Pose3()`, `Pose3(Rot3, point)` or `Pose3(4×4 matrix)`.
    #[new]
    #[pyo3(signature = (*args))]
    fn new(args: &Bound<'_, pyo3::types::PyTuple>) -> PyResult<Self> {
        let se3 = match args.len() {
            0 => Se3::identity(),
            1 => {
                let m = matrix_in(&args.get_item(0)?, Some(4), Some(4), "Pose3(matrix)")?;
                let r = rot3_of_matrix(&m);
                Se3::new(r, Vector3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]))
            }
            2 => {
                let r: Rot3 = args.get_item(0)?.extract()?;
                let t = fixed_vector_in(&args.get_item(1)?, 3, "Pose3(r, t): t")?;
                Se3::new(r.inner, Vector3::new(t[0], t[1], t[2]))
            }
            n => {
                return Err(pyo3::exceptions::PyTypeError::new_err(format!(
                    "Pose3 takes (), (Rot3, t) or (matrix), got {n} arguments"
                )))
            }
        };
        Ok(Self { inner: se3 })
    }
    fn x(&self) -> f64 {
        self.inner.translation.x
    }
    fn y(&self) -> f64 {
        self.inner.translation.y
    }
    fn z(&self) -> f64 {
        self.inner.translation.z
    }
    fn translation<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        vector_out(py, self.inner.translation.as_slice())
    }
    fn rotation(&self) -> Rot3 {
        Rot3 {
            inner: self.inner.rotation,
        }
    }
    fn matrix<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let r = self.inner.rotation_matrix();
        let t = self.inner.translation;
        let mut m = vec![0.0; 16];
        for i in 0..3 {
            for j in 0..3 {
                m[4 * i + j] = r[(i, j)];
            }
            m[4 * i + 3] = t[i];
        }
        m[15] = 1.0;
        matrix_out(py, 4, 4, &m)
    }
    fn compose(&self, other: &Pose3) -> Self {
        Self::from_se3(self.inner.compose(&other.inner))
    }
    fn __mul__(&self, other: &Pose3) -> Self {
        self.compose(other)
    }
    fn inverse(&self) -> Self {
        Self::from_se3(self.inner.inverse())
    }
    fn between(&self, other: &Pose3) -> Self {
        Self::from_se3(self.inner.between(&other.inner))
    }
    #[pyo3(name = "transformFrom")]
    fn transform_from<'py>(
        &self,
        py: Python<'py>,
        p: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let p = fixed_vector_in(p, 3, "Pose3.transformFrom: point")?;
        let q = self.inner.rotation * Vector3::new(p[0], p[1], p[2]) + self.inner.translation;
        vector_out(py, q.as_slice())
    }
    #[pyo3(name = "transformTo")]
    fn transform_to<'py>(
        &self,
        py: Python<'py>,
        p: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let p = fixed_vector_in(p, 3, "Pose3.transformTo: point")?;
        let q = self.inner.rotation.inverse()
            * (Vector3::new(p[0], p[1], p[2]) - self.inner.translation);
        vector_out(py, q.as_slice())
    }
    /// The distance to a point or to another pose's position.
    fn range(&self, target: &Bound<'_, PyAny>) -> PyResult<f64> {
        let p = match target.extract::<Pose3>() {
            Ok(pose) => pose.inner.translation,
            Err(_) => {
                let v = fixed_vector_in(target, 3, "Pose3.range: point")?;
                Vector3::new(v[0], v[1], v[2])
            }
        };
        Ok((p - self.inner.translation).norm())
    }
    /// The exponential of `(ω, v)` (GTSAM's order: rotation first).
    #[staticmethod]
    #[pyo3(name = "Expmap")]
    fn expmap(v: &Bound<'_, PyAny>) -> PyResult<Self> {
        let v = fixed_vector_in(v, 6, "Pose3.Expmap")?;
        Ok(Self::from_se3(Se3::exp(&swap_halves(&v))))
    }
    /// `(ω, v)`, GTSAM's order.
    #[staticmethod]
    #[pyo3(name = "Logmap")]
    fn logmap<'py>(py: Python<'py>, p: &Pose3) -> PyResult<Bound<'py, PyAny>> {
        let ours = p.inner.log();
        vector_out(py, swap_halves(ours.as_slice()).as_slice())
    }
    fn retract(&self, v: &Bound<'_, PyAny>) -> PyResult<Self> {
        Ok(self.compose(&Self::expmap(v)?))
    }
    #[pyo3(name = "localCoordinates")]
    fn local_coordinates<'py>(
        &self,
        py: Python<'py>,
        other: &Pose3,
    ) -> PyResult<Bound<'py, PyAny>> {
        Self::logmap(py, &self.between(other))
    }
    #[pyo3(signature = (other, tol = 1e-9))]
    fn equals(&self, other: &Pose3, tol: f64) -> bool {
        (self.inner.translation - other.inner.translation).amax() <= tol
            && so3::log(&(self.inner.rotation.inverse() * other.inner.rotation)).amax() <= tol
    }
    fn __repr__(&self) -> String {
        let t = self.inner.translation;
        let q = self.inner.rotation.quaternion();
        format!(
            "Pose3(R=Rot3.Quaternion({}, {}, {}, {}), t=[{}, {}, {}])",
            q.w, q.i, q.j, q.k, t.x, t.y, t.z
        )
    }
}
