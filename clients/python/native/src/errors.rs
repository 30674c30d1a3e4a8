//! The Python exceptions, one family under `FactordError` (a `RuntimeError`, as GTSAM's are), and
//! the mapping of the library's typed errors onto them. Keys in messages are written as GTSAM
//! writes symbols (`X(1)`), so a message names the variable as the script named it.

use pyo3::exceptions::PyRuntimeError;
use pyo3::prelude::*;

use factord::factors::EvaluationError;
use factord::problem::{evaluate_chi2, Problem, ProblemError};
use factord::solver::SolverError;

use crate::keys::key_name;

pyo3::create_exception!(
    _native,
    FactordError,
    PyRuntimeError,
    "Every error factord raises in process."
);
pyo3::create_exception!(
    _native,
    ValuesKeyDoesNotExist,
    FactordError,
    "A Values has no variable under the key asked for (GTSAM: ValuesKeyDoesNotExist)."
);
pyo3::create_exception!(
    _native,
    ValuesKeyAlreadyExists,
    FactordError,
    "Values.insert of a key that is already there (GTSAM: ValuesKeyAlreadyExists)."
);
pyo3::create_exception!(
    _native,
    ValuesIncorrectType,
    FactordError,
    "The variable under a key is of another type than the one asked for or needed (GTSAM: ValuesIncorrectType)."
);
pyo3::create_exception!(
    _native,
    DimensionMismatch,
    FactordError,
    "A noise model, matrix or vector has the wrong size for where it is used."
);
pyo3::create_exception!(
    _native,
    IndeterminantLinearSystemException,
    FactordError,
    "The linear system is singular at some variable: it is not constrained enough (GTSAM's name)."
);
pyo3::create_exception!(
    _native,
    InvalidNoiseModel,
    FactordError,
    "A covariance, information or sigma that does not define a Gaussian (not positive definite, not finite)."
);

/// A problem-building error as a Python exception.
pub fn problem_error(e: ProblemError) -> PyErr {
    match e {
        ProblemError::DuplicateVariable { key } => {
            ValuesKeyAlreadyExists::new_err(format!("variable {} already exists", key_name(key)))
        }
        ProblemError::UnknownVariable { key } => {
            ValuesKeyDoesNotExist::new_err(format!("no variable {}", key_name(key)))
        }
        ProblemError::FactorUnknownVariable { factor, key } => ValuesKeyDoesNotExist::new_err(
            format!("{factor}: no initial value for variable {}", key_name(key)),
        ),
        ProblemError::FactorWrongKind {
            factor,
            key,
            expected,
            found,
        } => ValuesIncorrectType::new_err(format!(
            "{factor}: variable {} is a {}, the factor needs a {}",
            key_name(key),
            type_name(found),
            type_name(expected)
        )),
        ProblemError::FactorRepeatedVariable { factor, key } => FactordError::new_err(format!(
            "{factor}: touches variable {} twice",
            key_name(key)
        )),
        ProblemError::BadInformation { factor, reason } => {
            InvalidNoiseModel::new_err(format!("{factor}: {reason}"))
        }
        ProblemError::NonFiniteVariable { key } => {
            FactordError::new_err(format!("variable {} has a non-finite value", key_name(key)))
        }
        ProblemError::NonFiniteMeasurement { factor } => FactordError::new_err(format!(
            "{factor}: the residual is not finite at the initial values"
        )),
    }
}

/// A solver error as a Python exception.
pub fn solver_error(e: SolverError) -> PyErr {
    match e {
        SolverError::IndeterminateSystem { keys } => {
            let names: Vec<String> = keys.iter().map(|&k| key_name(k)).collect();
            IndeterminantLinearSystemException::new_err(format!(
                "indeterminant linear system near variable(s) {}: they are not constrained by enough factors (add a prior, or the missing measurements)",
                names.join(", ")
            ))
        }
        SolverError::Evaluation(e) => evaluation_error(e),
        other => FactordError::new_err(other.to_string()),
    }
}

/// A factor that could not be evaluated: the exception its Python error function raised, when
/// one did (`custom.rs`), else the library's message.
pub fn evaluation_error(e: EvaluationError) -> PyErr {
    crate::custom::take_raised().unwrap_or_else(|| FactordError::new_err(e.to_string()))
}

/// `Σ ρ(‖R e‖²)` of `problem` at its values, or why a factor could not be evaluated.
pub fn chi2_of(problem: &Problem) -> PyResult<f64> {
    evaluate_chi2(problem.factors(), &problem.values).map_err(evaluation_error)
}

/// GTSAM's type name of one of the library's variable kinds.
pub fn type_name(kind: &str) -> &str {
    match kind {
        "se2" => "Pose2",
        "se3" => "Pose3",
        "point2" => "Point2",
        "point3" => "Point3",
        "snavely_camera" => "SnavelyCamera",
        other => other,
    }
}

/// Registers the exceptions on the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("FactordError", py.get_type::<FactordError>())?;
    m.add(
        "ValuesKeyDoesNotExist",
        py.get_type::<ValuesKeyDoesNotExist>(),
    )?;
    m.add(
        "ValuesKeyAlreadyExists",
        py.get_type::<ValuesKeyAlreadyExists>(),
    )?;
    m.add("ValuesIncorrectType", py.get_type::<ValuesIncorrectType>())?;
    m.add("DimensionMismatch", py.get_type::<DimensionMismatch>())?;
    m.add(
        "IndeterminantLinearSystemException",
        py.get_type::<IndeterminantLinearSystemException>(),
    )?;
    m.add("InvalidNoiseModel", py.get_type::<InvalidNoiseModel>())?;
    Ok(())
}
