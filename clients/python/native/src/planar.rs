//! `Rot2` and `Pose2` with GTSAM's constructors and methods, over the library's `Se2`. Points
//! are plain numpy arrays, as in GTSAM 4's Python wrapper.

use pyo3::prelude::*;

use factord::geometry::{wrap_angle, Se2};

use crate::arrays::{fixed_vector_in, matrix_in, matrix_out, vector_out};

#[pyclass(module = "factord", name = "Rot2", from_py_object)]
#[derive(Clone, Copy, Debug)]
pub struct Rot2 {
    pub theta: f64,
}

#[pymethods]
impl Rot2 {
    #[new]
    #[pyo3(signature = (theta = 0.0))]
    fn new(theta: f64) -> Self {
        Self {
            theta: wrap_angle(theta),
        }
    }
    #[staticmethod]
    #[pyo3(name = "fromAngle")]
    fn from_angle(theta: f64) -> Self {
        Self::new(theta)
    }
    #[staticmethod]
    #[pyo3(name = "fromDegrees")]
    fn from_degrees(degrees: f64) -> Self {
        Self::new(degrees.to_radians())
    }
    #[staticmethod]
    #[pyo3(name = "fromCosSin")]
    fn from_cos_sin(c: f64, s: f64) -> Self {
        Self::new(s.atan2(c))
    }
    fn theta(&self) -> f64 {
        self.theta
    }
    fn degrees(&self) -> f64 {
        self.theta.to_degrees()
    }
    fn c(&self) -> f64 {
        self.theta.cos()
    }
    fn s(&self) -> f64 {
        self.theta.sin()
    }
    fn matrix<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let (s, c) = self.theta.sin_cos();
        matrix_out(py, 2, 2, &[c, -s, s, c])
    }
    fn inverse(&self) -> Self {
        Self::new(-self.theta)
    }
    fn compose(&self, other: &Rot2) -> Self {
        Self::new(self.theta + other.theta)
    }
    fn between(&self, other: &Rot2) -> Self {
        Self::new(other.theta - self.theta)
    }
    fn __mul__(&self, other: &Rot2) -> Self {
        self.compose(other)
    }
    fn rotate<'py>(&self, py: Python<'py>, p: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyAny>> {
        let p = fixed_vector_in(p, 2, "Rot2.rotate: point")?;
        let (s, c) = self.theta.sin_cos();
        vector_out(py, &[c * p[0] - s * p[1], s * p[0] + c * p[1]])
    }
    fn unrotate<'py>(&self, py: Python<'py>, p: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyAny>> {
        self.inverse().rotate(py, p)
    }
    #[pyo3(signature = (other, tol = 1e-9))]
    fn equals(&self, other: &Rot2, tol: f64) -> bool {
        wrap_angle(self.theta - other.theta).abs() <= tol
    }
    fn __repr__(&self) -> String {
        format!("Rot2(theta={})", self.theta)
    }
}

#[pyclass(module = "factord", name = "Pose2", from_py_object)]
#[derive(Clone, Copy, Debug)]
pub struct Pose2 {
    pub inner: Se2,
}

impl Pose2 {
    pub fn from_se2(inner: Se2) -> Self {
        Self { inner }
    }
}

#[pymethods]
impl Pose2 {
    /// `Pose2()`, `Pose2(x, y, theta)`, `Pose2(Rot2, point)` or `Pose2(3×3 matrix)`.
    #[new]
    #[pyo3(signature = (*args))]
    fn new(args: &Bound<'_, pyo3::types::PyTuple>) -> PyResult<Self> {
        let se2 = match args.len() {
            0 => Se2::identity(),
            1 => {
                let m = matrix_in(&args.get_item(0)?, Some(3), Some(3), "Pose2(matrix)")?;
                Se2::new(m[(0, 2)], m[(1, 2)], m[(1, 0)].atan2(m[(0, 0)]))
            }
            2 => {
                let r: Rot2 = args.get_item(0)?.extract()?;
                let t = fixed_vector_in(&args.get_item(1)?, 2, "Pose2(r, t): t")?;
                Se2::new(t[0], t[1], r.theta)
            }
            3 => {
                let (x, y, theta): (f64, f64, f64) = args.extract()?;
                Se2::new(x, y, theta)
            }
            n => {
                return Err(pyo3::exceptions::PyTypeError::new_err(format!(
                    "Pose2 takes (), (x, y, theta), (Rot2, t) or (matrix), got {n} arguments"
                )))
            }
        };
        Ok(Self { inner: se2 })
    }
    fn x(&self) -> f64 {
        self.inner.x
    }
    fn y(&self) -> f64 {
        self.inner.y
    }
    fn theta(&self) -> f64 {
        self.inner.theta
    }
    fn translation<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        vector_out(py, &[self.inner.x, self.inner.y])
    }
    fn rotation(&self) -> Rot2 {
        Rot2::new(self.inner.theta)
    }
    fn matrix<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let (s, c) = self.inner.theta.sin_cos();
        let (x, y) = (self.inner.x, self.inner.y);
        matrix_out(py, 3, 3, &[c, -s, x, s, c, y, 0.0, 0.0, 1.0])
    }
    fn compose(&self, other: &Pose2) -> Self {
        Self::from_se2(self.inner.compose(&other.inner))
    }
    fn __mul__(&self, other: &Pose2) -> Self {
        self.compose(other)
    }
    fn inverse(&self) -> Self {
        Self::from_se2(self.inner.inverse())
    }
    fn between(&self, other: &Pose2) -> Self {
        Self::from_se2(self.inner.between(&other.inner))
    }
    #[pyo3(name = "transformFrom")]
    fn transform_from<'py>(
        &self,
        py: Python<'py>,
        p: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let p = fixed_vector_in(p, 2, "Pose2.transformFrom: point")?;
        let (s, c) = self.inner.theta.sin_cos();
        vector_out(
            py,
            &[
                c * p[0] - s * p[1] + self.inner.x,
                s * p[0] + c * p[1] + self.inner.y,
            ],
        )
    }
    #[pyo3(name = "transformTo")]
    fn transform_to<'py>(
        &self,
        py: Python<'py>,
        p: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let p = fixed_vector_in(p, 2, "Pose2.transformTo: point")?;
        let (s, c) = self.inner.theta.sin_cos();
        let (dx, dy) = (p[0] - self.inner.x, p[1] - self.inner.y);
        vector_out(py, &[c * dx + s * dy, -s * dx + c * dy])
    }
    /// The bearing of a point (a numpy 2-vector) or of another pose's position, as a `Rot2`.
    fn bearing(&self, target: &Bound<'_, PyAny>) -> PyResult<Rot2> {
        let [dx, dy] = self.local_of(target)?;
        Ok(Rot2::new(dy.atan2(dx)))
    }
    /// The distance to a point or to another pose's position.
    fn range(&self, target: &Bound<'_, PyAny>) -> PyResult<f64> {
        let [dx, dy] = self.local_of(target)?;
        Ok(dx.hypot(dy))
    }
    #[staticmethod]
    #[pyo3(name = "Expmap")]
    fn expmap(v: &Bound<'_, PyAny>) -> PyResult<Self> {
        let v = fixed_vector_in(v, 3, "Pose2.Expmap")?;
        Ok(Self::from_se2(Se2::exp([v[0], v[1], v[2]])))
    }
    #[staticmethod]
    #[pyo3(name = "Logmap")]
    fn logmap<'py>(py: Python<'py>, p: &Pose2) -> PyResult<Bound<'py, PyAny>> {
        vector_out(py, &p.inner.log())
    }
    /// `self ⊕ v` with GTSAM's retraction (the exponential map on the right).
    fn retract(&self, v: &Bound<'_, PyAny>) -> PyResult<Self> {
        Ok(self.compose(&Self::expmap(v)?))
    }
    #[pyo3(name = "localCoordinates")]
    fn local_coordinates<'py>(
        &self,
        py: Python<'py>,
        other: &Pose2,
    ) -> PyResult<Bound<'py, PyAny>> {
        vector_out(py, &self.inner.between(&other.inner).log())
    }
    #[pyo3(signature = (other, tol = 1e-9))]
    fn equals(&self, other: &Pose2, tol: f64) -> bool {
        (self.inner.x - other.inner.x).abs() <= tol
            && (self.inner.y - other.inner.y).abs() <= tol
            && wrap_angle(self.inner.theta - other.inner.theta).abs() <= tol
    }
    fn __repr__(&self) -> String {
        format!(
            "Pose2(x={:?}, y={:?}, theta={:?})",
            self.inner.x, self.inner.y, self.inner.theta
        )
    }
}

impl Pose2 {
    /// A target point (or pose position) in this pose's frame.
    fn local_of(&self, target: &Bound<'_, PyAny>) -> PyResult<[f64; 2]> {
        let p = match target.extract::<Pose2>() {
            Ok(pose) => vec![pose.inner.x, pose.inner.y],
            Err(_) => fixed_vector_in(target, 2, "Pose2: point")?,
        };
        let (s, c) = self.inner.theta.sin_cos();
        let (dx, dy) = (p[0] - self.inner.x, p[1] - self.inner.y);
        Ok([c * dx + s * dy, -s * dx + c * dy])
    }
}
