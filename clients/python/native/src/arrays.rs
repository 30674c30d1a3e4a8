//! numpy in and out without a compiled numpy dependency: everything coming in goes through
//! `numpy.asarray(x, dtype=float)` (lists, tuples, arrays and numpy scalars alike) and leaves as
//! a `numpy.ndarray` of float64.

use nalgebra::DMatrix;
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;

use crate::errors::DimensionMismatch;

fn numpy(py: Python<'_>) -> PyResult<&Bound<'_, PyModule>> {
    static NUMPY: PyOnceLock<Py<PyModule>> = PyOnceLock::new();
    NUMPY
        .get_or_try_init(py, || py.import("numpy").map(Bound::unbind))
        .map(|m| m.bind(py))
}

/// A 1-D float64 array.
pub fn vector_out<'py>(py: Python<'py>, values: &[f64]) -> PyResult<Bound<'py, PyAny>> {
    numpy(py)?.getattr("array")?.call1((values.to_vec(),))
}

/// A `rows × cols` float64 array from row-major `values`.
pub fn matrix_out<'py>(
    py: Python<'py>,
    rows: usize,
    cols: usize,
    values: &[f64],
) -> PyResult<Bound<'py, PyAny>> {
    let nested: Vec<Vec<f64>> = (0..rows)
        .map(|r| values[r * cols..(r + 1) * cols].to_vec())
        .collect();
    numpy(py)?.getattr("array")?.call1((nested,))
}

/// A `DMatrix` as a float64 array.
pub fn dmatrix_out<'py>(py: Python<'py>, m: &DMatrix<f64>) -> PyResult<Bound<'py, PyAny>> {
    let row_major: Vec<f64> = (0..m.nrows())
        .flat_map(|r| (0..m.ncols()).map(move |c| m[(r, c)]))
        .collect();
    matrix_out(py, m.nrows(), m.ncols(), &row_major)
}

/// `obj` as a float array: its shape and its values, row-major. Not one (a string, a ragged
/// list): a `TypeError` naming `what`.
fn as_array(obj: &Bound<'_, PyAny>, what: &str) -> PyResult<(Vec<usize>, Vec<f64>)> {
    let py = obj.py();
    let array = numpy(py)?
        .getattr("asarray")?
        .call1((obj, py.import("builtins")?.getattr("float")?))
        .map_err(|e| {
            pyo3::exceptions::PyTypeError::new_err(format!("{what}: not an array of numbers ({e})"))
        })?;
    let shape: Vec<usize> = array.getattr("shape")?.extract()?;
    let flat: Vec<f64> = array
        .call_method0("ravel")?
        .call_method0("tolist")?
        .extract()?;
    Ok((shape, flat))
}

/// A vector of any length (1-D).
pub fn vector_in(obj: &Bound<'_, PyAny>, what: &str) -> PyResult<Vec<f64>> {
    let (shape, flat) = as_array(obj, what)?;
    if shape.len() != 1 {
        return Err(DimensionMismatch::new_err(format!(
            "{what}: expected a vector, got an array of shape {shape:?}"
        )));
    }
    Ok(flat)
}

/// A vector of exactly `len` numbers.
pub fn fixed_vector_in(obj: &Bound<'_, PyAny>, len: usize, what: &str) -> PyResult<Vec<f64>> {
    let v = vector_in(obj, what)?;
    if v.len() != len {
        return Err(DimensionMismatch::new_err(format!(
            "{what}: expected {len} numbers, got {}",
            v.len()
        )));
    }
    Ok(v)
}

/// A matrix of exactly `rows × cols`, or square of any size when `rows`/`cols` are `None`.
pub fn matrix_in(
    obj: &Bound<'_, PyAny>,
    rows: Option<usize>,
    cols: Option<usize>,
    what: &str,
) -> PyResult<DMatrix<f64>> {
    let (shape, flat) = as_array(obj, what)?;
    let ok = shape.len() == 2
        && rows.is_none_or(|r| shape[0] == r)
        && cols.is_none_or(|c| shape[1] == c)
        && (rows.is_some() || shape[0] == shape[1]);
    if !ok {
        let wanted = match (rows, cols) {
            (Some(r), Some(c)) => format!("{r}×{c}"),
            _ => "square".to_string(),
        };
        return Err(DimensionMismatch::new_err(format!(
            "{what}: expected a {wanted} matrix, got an array of shape {shape:?}"
        )));
    }
    Ok(DMatrix::from_row_slice(shape[0], shape[1], &flat))
}
