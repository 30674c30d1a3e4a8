//! `Values`: variables under keys, in key order as GTSAM iterates them. Poses are `Pose2`/`Pose3`
//! objects; points go in and come out as numpy arrays (a 2-vector is a `Point2`, a 3-vector a
//! `Point3`).

use std::collections::BTreeMap;

use nalgebra::{DMatrix, Vector2, Vector3};
use pyo3::prelude::*;

use factord::geometry::{Point2, Point3, Se2, Se3, SnavelyCamera as LibraryCamera};
use factord::problem::Key;
use factord::variables::Variable;

use crate::arrays::{matrix_out, vector_in, vector_out};
use crate::camera::SnavelyCamera;
use crate::errors::{
    type_name, ValuesIncorrectType, ValuesKeyAlreadyExists, ValuesKeyDoesNotExist,
};
use crate::keys::key_name;
use crate::planar::Pose2;
use crate::spatial::Pose3;

#[pyclass(module = "factord", name = "Values")]
#[derive(Debug, Default)]
pub struct Values {
    pub map: BTreeMap<Key, Box<dyn Variable>>,
}

impl Clone for Values {
    fn clone(&self) -> Self {
        Self {
            map: self.map.iter().map(|(&k, v)| (k, v.clone_box())).collect(),
        }
    }
}

/// A Python value as one of the library's variables.
pub fn variable_of(value: &Bound<'_, PyAny>, key: Key) -> PyResult<Box<dyn Variable>> {
    if let Ok(p) = value.extract::<Pose2>() {
        return Ok(Box::new(p.inner));
    }
    if let Ok(p) = value.extract::<Pose3>() {
        return Ok(Box::new(p.inner));
    }
    if let Ok(c) = value.extract::<SnavelyCamera>() {
        return Ok(Box::new(c.inner));
    }
    let v = vector_in(value, &format!("value of {}", key_name(key))).map_err(|_| {
        ValuesIncorrectType::new_err(format!(
            "value of {}: a Pose2, Pose3, SnavelyCamera or a point (numpy 2- or 3-vector) is needed, got {}",
            key_name(key),
            value
                .get_type()
                .name()
                .map(|n| n.to_string())
                .unwrap_or_default()
        ))
    })?;
    let variable: Box<dyn Variable> = match v.len() {
        2 => Box::new(Point2(Vector2::new(v[0], v[1]))),
        3 => Box::new(Point3(Vector3::new(v[0], v[1], v[2]))),
        n => {
            return Err(ValuesIncorrectType::new_err(format!(
                "value of {}: a point has 2 or 3 coordinates, got {n}",
                key_name(key)
            )))
        }
    };
    Ok(variable)
}

/// One of the library's variables as a Python value.
pub fn object_of(py: Python<'_>, variable: &dyn Variable) -> PyResult<Py<PyAny>> {
    let any = variable.as_any();
    if let Some(p) = any.downcast_ref::<Se2>() {
        return Ok(Py::new(py, Pose2::from_se2(*p))?.into_any());
    }
    if let Some(p) = any.downcast_ref::<Se3>() {
        return Ok(Py::new(py, Pose3::from_se3(*p))?.into_any());
    }
    if let Some(c) = any.downcast_ref::<LibraryCamera>() {
        return Ok(Py::new(py, SnavelyCamera { inner: *c })?.into_any());
    }
    if let Some(p) = any.downcast_ref::<Point2>() {
        return Ok(vector_out(py, p.0.as_slice())?.unbind());
    }
    if let Some(p) = any.downcast_ref::<Point3>() {
        return Ok(vector_out(py, p.0.as_slice())?.unbind());
    }
    Err(ValuesIncorrectType::new_err(format!(
        "a variable of kind {} has no Python type",
        variable.kind()
    )))
}

impl Values {
    /// The variable under `key`, or `ValuesKeyDoesNotExist` naming it.
    pub fn get(&self, key: Key) -> PyResult<&dyn Variable> {
        self.map.get(&key).map(|v| v.as_ref()).ok_or_else(|| {
            ValuesKeyDoesNotExist::new_err(format!(
                "Values has no variable {} (key {key})",
                key_name(key)
            ))
        })
    }

    /// The variable under `key` as `T`, or `ValuesIncorrectType` naming what it is.
    pub fn get_as<T: Variable>(&self, key: Key, wanted: &str) -> PyResult<&T> {
        let v = self.get(key)?;
        v.as_any().downcast_ref::<T>().ok_or_else(|| {
            ValuesIncorrectType::new_err(format!(
                "variable {} is a {}, not a {wanted}",
                key_name(key),
                type_name(v.kind())
            ))
        })
    }

    /// Row-major rows of every variable of kind `kind`, `width` numbers each, and their keys.
    fn rows(
        &self,
        kind: &str,
        width: usize,
        row: impl Fn(&dyn Variable) -> Vec<f64>,
    ) -> (Vec<Key>, Vec<f64>) {
        let mut keys = Vec::new();
        let mut out = Vec::new();
        for (&k, v) in &self.map {
            if v.kind() == kind {
                keys.push(k);
                let r = row(v.as_ref());
                debug_assert_eq!(r.len(), width);
                out.extend(r);
            }
        }
        (keys, out)
    }
}

#[pymethods]
impl Values {
    #[new]
    #[pyo3(signature = (other = None))]
    fn new(other: Option<&Values>) -> Self {
        other.cloned().unwrap_or_default()
    }
    /// `insert(key, value)`, or `insert(values)` of every variable of another `Values`.
    #[pyo3(signature = (key_or_values, value = None))]
    fn insert(
        &mut self,
        key_or_values: &Bound<'_, PyAny>,
        value: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<()> {
        match value {
            Some(value) => {
                let key: Key = key_or_values.extract()?;
                if self.map.contains_key(&key) {
                    return Err(ValuesKeyAlreadyExists::new_err(format!(
                        "Values already has a variable {}",
                        key_name(key)
                    )));
                }
                let v = variable_of(value, key)?;
                self.map.insert(key, v);
                Ok(())
            }
            None => {
                let other: PyRef<'_, Values> = key_or_values.extract()?;
                if let Some(k) = other.map.keys().find(|k| self.map.contains_key(k)) {
                    return Err(ValuesKeyAlreadyExists::new_err(format!(
                        "Values already has a variable {}",
                        key_name(*k)
                    )));
                }
                for (&k, v) in &other.map {
                    self.map.insert(k, v.clone_box());
                }
                Ok(())
            }
        }
    }
    /// Replaces the variable under `key` with a value of the same type.
    fn update(&mut self, key: Key, value: &Bound<'_, PyAny>) -> PyResult<()> {
        let old_kind = self.get(key)?.kind();
        let v = variable_of(value, key)?;
        if v.kind() != old_kind {
            return Err(ValuesIncorrectType::new_err(format!(
                "variable {} is a {}, update gave a {}",
                key_name(key),
                type_name(old_kind),
                type_name(v.kind())
            )));
        }
        self.map.insert(key, v);
        Ok(())
    }
    fn insert_or_assign(&mut self, key: Key, value: &Bound<'_, PyAny>) -> PyResult<()> {
        let v = variable_of(value, key)?;
        self.map.insert(key, v);
        Ok(())
    }
    fn erase(&mut self, key: Key) -> PyResult<()> {
        self.get(key)?;
        self.map.remove(&key);
        Ok(())
    }
    fn exists(&self, key: Key) -> bool {
        self.map.contains_key(&key)
    }
    fn __contains__(&self, key: Key) -> bool {
        self.exists(key)
    }
    fn keys(&self) -> Vec<Key> {
        self.map.keys().copied().collect()
    }
    fn size(&self) -> usize {
        self.map.len()
    }
    fn __len__(&self) -> usize {
        self.map.len()
    }
    fn empty(&self) -> bool {
        self.map.is_empty()
    }
    fn clear(&mut self) {
        self.map.clear();
    }
    fn copy(&self) -> Self {
        self.clone()
    }
    fn __copy__(&self) -> Self {
        self.clone()
    }
    fn __deepcopy__(&self, _memo: &Bound<'_, PyAny>) -> Self {
        self.clone()
    }
    /// The value under `key`, of whatever type it is.
    fn at(&self, py: Python<'_>, key: Key) -> PyResult<Py<PyAny>> {
        object_of(py, self.get(key)?)
    }
    #[pyo3(name = "atPose2")]
    fn at_pose2(&self, key: Key) -> PyResult<Pose2> {
        Ok(Pose2::from_se2(*self.get_as::<Se2>(key, "Pose2")?))
    }
    #[pyo3(name = "atPose3")]
    fn at_pose3(&self, key: Key) -> PyResult<Pose3> {
        Ok(Pose3::from_se3(*self.get_as::<Se3>(key, "Pose3")?))
    }
    #[pyo3(name = "atSnavelyCamera")]
    fn at_snavely_camera(&self, key: Key) -> PyResult<SnavelyCamera> {
        Ok(SnavelyCamera {
            inner: *self.get_as::<LibraryCamera>(key, "SnavelyCamera")?,
        })
    }
    #[pyo3(name = "atPoint2")]
    fn at_point2<'py>(&self, py: Python<'py>, key: Key) -> PyResult<Bound<'py, PyAny>> {
        vector_out(py, self.get_as::<Point2>(key, "Point2")?.0.as_slice())
    }
    #[pyo3(name = "atPoint3")]
    fn at_point3<'py>(&self, py: Python<'py>, key: Key) -> PyResult<Bound<'py, PyAny>> {
        vector_out(py, self.get_as::<Point3>(key, "Point3")?.0.as_slice())
    }
    /// `(keys, N×3 array of x, y, θ)` of every `Pose2` (`utilities.extractPose2` uses it).
    fn _pose2_rows<'py>(&self, py: Python<'py>) -> PyResult<(Vec<Key>, Bound<'py, PyAny>)> {
        let (keys, rows) = self.rows("se2", 3, |v| {
            let p = v.as_any().downcast_ref::<Se2>().expect("kind se2 is Se2");
            vec![p.x, p.y, p.theta]
        });
        let n = keys.len();
        Ok((keys, matrix_out(py, n, 3, &rows)?))
    }
    /// `(keys, N×12 array of R row-major then t)` of every `Pose3`, GTSAM's `extractPose3` layout.
    fn _pose3_rows<'py>(&self, py: Python<'py>) -> PyResult<(Vec<Key>, Bound<'py, PyAny>)> {
        let (keys, rows) = self.rows("se3", 12, |v| {
            let p = v.as_any().downcast_ref::<Se3>().expect("kind se3 is Se3");
            let r = p.rotation_matrix();
            let t = p.translation;
            let mut row: Vec<f64> = (0..9).map(|k| r[(k / 3, k % 3)]).collect();
            row.extend_from_slice(t.as_slice());
            row
        });
        let n = keys.len();
        Ok((keys, matrix_out(py, n, 12, &rows)?))
    }
    /// `(keys, N×d array)` of every point of dimension `d` (2 or 3).
    fn _point_rows<'py>(
        &self,
        py: Python<'py>,
        d: usize,
    ) -> PyResult<(Vec<Key>, Bound<'py, PyAny>)> {
        let kind = match d {
            2 => "point2",
            3 => "point3",
            _ => {
                return Err(pyo3::exceptions::PyValueError::new_err(format!(
                    "points have 2 or 3 coordinates, not {d}"
                )))
            }
        };
        let (keys, rows) = self.rows(kind, d, |v| {
            if let Some(p) = v.as_any().downcast_ref::<Point2>() {
                p.0.as_slice().to_vec()
            } else {
                let p = v
                    .as_any()
                    .downcast_ref::<Point3>()
                    .expect("kind point3 is Point3");
                p.0.as_slice().to_vec()
            }
        });
        let n = keys.len();
        Ok((keys, matrix_out(py, n, d, &rows)?))
    }
    fn __repr__(&self) -> String {
        format!("Values with {} variables", self.map.len())
    }
}

/// The matrix taking a variable's library tangent to GTSAM's: `ξ = T δ`.
pub fn to_gtsam_tangent(variable: &dyn Variable) -> DMatrix<f64> {
    let n = variable.tangent_dim();
    if let Some(p) = variable.as_any().downcast_ref::<Se2>() {
        // The library moves a Pose2 in the world frame, GTSAM in its body frame: ξ_t = Rᵀ δt.
        let (s, c) = p.theta.sin_cos();
        return DMatrix::from_row_slice(3, 3, &[c, s, 0.0, -s, c, 0.0, 0.0, 0.0, 1.0]);
    }
    if variable.kind() == "se3" {
        // The library's (v, ω) is GTSAM's (ω, v) to first order.
        let perm = [3, 4, 5, 0, 1, 2];
        return DMatrix::from_fn(6, 6, |r, c| if perm[r] == c { 1.0 } else { 0.0 });
    }
    DMatrix::identity(n, n)
}
