//! `readG2o`, `writeG2o` and `loadBal` through the library's readers and writers: the same records, the
//! same information handling and the same errors as `factord solve` (TORO and GTSAM's landmark
//! text are read too, detected by content).

use std::path::PathBuf;
use std::sync::Arc;

use pyo3::prelude::*;

use factord::io::{self, Dimension, PoseGraph};

use crate::errors::FactordError;
use crate::factors::from_library;
use crate::graph::{build_problem, NonlinearFactorGraph};
use crate::values::Values;

/// `(graph, initial)` of a g2o file (GTSAM: `readG2o(filename, is3D)`). `is3D` is checked
/// against what the file holds.
#[pyfunction]
#[pyo3(name = "readG2o", signature = (filename, is3D = false))]
#[allow(non_snake_case)]
pub fn read_g2o(
    py: Python<'_>,
    filename: PathBuf,
    is3D: bool,
) -> PyResult<(NonlinearFactorGraph, Values)> {
    let mut loaded = io::load(&filename, None).map_err(|e| FactordError::new_err(e.to_string()))?;
    let file_is_3d = loaded.dimension == Dimension::Three;
    if file_is_3d != is3D && !loaded.problem.values.is_empty() {
        return Err(FactordError::new_err(format!(
            "readG2o({}, is3D={}): the file holds a {} graph",
            filename.display(),
            if is3D { "True" } else { "False" },
            if file_is_3d { "3D" } else { "2D" }
        )));
    }
    library_graph(py, &mut loaded.problem)
}

/// `(graph, initial)` of a BAL file (factord's own call: GTSAM's `readBal` answers an `SfmData`
/// in another camera frame): camera `i` is key `i` (a `SnavelyCamera`), point `j` key
/// `cameras + j`, each observation a `SnavelyReprojectionFactor` with unit noise (BAL's cost is
/// `graph.error`, ½Σ‖e‖²). The same reader as `factord ba`.
#[pyfunction]
#[pyo3(name = "loadBal")]
pub fn load_bal(py: Python<'_>, filename: PathBuf) -> PyResult<(NonlinearFactorGraph, Values)> {
    let mut loaded = io::bal::load(&filename).map_err(|e| FactordError::new_err(e.to_string()))?;
    library_graph(py, &mut loaded.problem)
}

/// The factors (taken) and values of a library problem as a graph and a `Values`.
fn library_graph(
    py: Python<'_>,
    problem: &mut factord::problem::Problem,
) -> PyResult<(NonlinearFactorGraph, Values)> {
    let entries = problem.take_factors(|_| true);
    let mut graph = NonlinearFactorGraph::default();
    for e in entries {
        let data = from_library(py, e.factor, e.sqrt_information, e.robust, e.label)?;
        graph.factors.push(Some(Arc::new(data)));
    }
    let v = &problem.values;
    let values = Values {
        map: (0..v.len())
            .map(|i| (v.key(i), v.variable(i).clone_box()))
            .collect(),
    };
    Ok((graph, values))
}

/// Writes `graph` with the vertices of `estimate` as g2o (GTSAM: `writeG2o`). Factors without a
/// g2o record (priors) are written as comments, as `factord solve --out` does.
#[pyfunction]
#[pyo3(name = "writeG2o")]
pub fn write_g2o(
    graph: &NonlinearFactorGraph,
    estimate: &Values,
    filename: PathBuf,
) -> PyResult<()> {
    let problem = build_problem(estimate, graph.present())?;
    let dimension = if estimate.map.values().any(|v| v.kind() == "se3") {
        Dimension::Three
    } else {
        Dimension::Two
    };
    let pose_graph = PoseGraph {
        vertex_order: estimate.map.keys().copied().collect(),
        problem,
        dimension,
    };
    io::g2o::write(&pose_graph, &filename).map_err(|e| FactordError::new_err(e.to_string()))
}
