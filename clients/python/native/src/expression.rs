//! `FactorType`: a user-defined factor type compiled by the library's expression compiler, the
//! one a server session compiles its `factor_types` with: the residual is a JSON expression
//! tree, type-checked, lowered to a tape and differentiated in forward mode (its Jacobian
//! checked against central differences when compiled). `factord.expressions` (Python) traces a
//! Python function into that tree; this class takes the tree as the server's wire would.
//!
//! Factors of a type are built with one Python value per declared parameter, in declared order
//! (`se2`: a `Pose2`, `se3`: a `Pose3`, points and vectors: numpy arrays, `scalar`: a float);
//! the wire's flat measurement is assembled from them here.

use std::sync::Arc;

use pyo3::prelude::*;

use factord::factors::expression::{ExpressionType, FactorTypeDefinition};
use factord::problem::Key;

use crate::arrays::{fixed_vector_in, vector_in};
use crate::errors::{DimensionMismatch, FactordError};
use crate::factors::{FactorClass, FactorData, NonlinearFactor};
use crate::noise::NoiseModel;
use crate::planar::Pose2;
use crate::spatial::Pose3;

/// A compiled factor type (the library's `ExpressionType`).
#[pyclass(module = "factord._native", name = "FactorType", frozen)]
pub struct FactorType {
    compiled: Arc<ExpressionType>,
}

/// The wire encoding of one parameter's Python value.
fn encode_parameter(
    value: &Bound<'_, PyAny>,
    kind: &str,
    len: Option<usize>,
    what: &str,
) -> PyResult<Vec<f64>> {
    match kind {
        "scalar" => Ok(vec![value.extract::<f64>().map_err(|_| {
            FactordError::new_err(format!("{what}: a scalar parameter takes a float"))
        })?]),
        "se2" => {
            let p = value.extract::<Pose2>().map_err(|_| {
                FactordError::new_err(format!("{what}: an se2 parameter takes a Pose2"))
            })?;
            Ok(vec![p.inner.x, p.inner.y, p.inner.theta])
        }
        "se3" => {
            let p = value.extract::<Pose3>().map_err(|_| {
                FactordError::new_err(format!("{what}: an se3 parameter takes a Pose3"))
            })?;
            let t = p.inner.translation;
            let q = p.inner.rotation;
            Ok(vec![t.x, t.y, t.z, q.i, q.j, q.k, q.w])
        }
        "point2" => fixed_vector_in(value, 2, what),
        "point3" => fixed_vector_in(value, 3, what),
        "vector" => match len {
            Some(n) => fixed_vector_in(value, n, what),
            None => vector_in(value, what),
        },
        other => Err(FactordError::new_err(format!(
            "{what}: parameters of kind {other} are not supported"
        ))),
    }
}

#[pymethods]
impl FactorType {
    /// Compiles a definition given as JSON text (the wire's `factor_types[i]`).
    #[new]
    fn new(definition_json: &str) -> PyResult<Self> {
        let definition: FactorTypeDefinition = serde_json::from_str(definition_json)
            .map_err(|e| FactordError::new_err(format!("factor type definition: {e}")))?;
        let name = definition.name.clone();
        let compiled = ExpressionType::compile(definition)
            .map_err(|e| FactordError::new_err(format!("factor type {name:?}: {e}")))?;
        Ok(Self { compiled })
    }

    /// A factor of this type on `keys` (in the order of the declared variables), measuring
    /// `parameters` (one value per declared parameter, in order), weighed by `noise`.
    fn factor(
        &self,
        keys: Vec<Key>,
        parameters: Vec<Bound<'_, PyAny>>,
        noise: &NoiseModel,
    ) -> PyResult<NonlinearFactor> {
        let definition = &self.compiled.definition;
        let name = &definition.name;
        if keys.len() != definition.variables.len() {
            return Err(FactordError::new_err(format!(
                "{name}: {} keys given, the type connects {} variables",
                keys.len(),
                definition.variables.len()
            )));
        }
        if parameters.len() != definition.parameters.len() {
            return Err(FactordError::new_err(format!(
                "{name}: {} parameters given, the type declares {}",
                parameters.len(),
                definition.parameters.len()
            )));
        }
        let mut measurement = Vec::with_capacity(self.compiled.measurement_len());
        for (value, declared) in parameters.iter().zip(&definition.parameters) {
            let what = format!("{name}: parameter `{}`", declared.name);
            measurement.extend(encode_parameter(
                value,
                &declared.kind,
                declared.len,
                &what,
            )?);
        }
        if measurement.len() != self.compiled.measurement_len() {
            return Err(DimensionMismatch::new_err(format!(
                "{name}: the parameters encode {} numbers, the type takes {}",
                measurement.len(),
                self.compiled.measurement_len()
            )));
        }
        let factor = self
            .compiled
            .build(&keys, &measurement)
            .map_err(|e| FactordError::new_err(format!("{name}: {e}")))?;
        let data = FactorData::new(Box::new(factor), noise, FactorClass::Other, None)?;
        Ok(NonlinearFactor {
            data: Arc::new(data),
        })
    }

    #[getter]
    fn name(&self) -> String {
        self.compiled.name().to_string()
    }
    /// The residual's length: the noise model's dimension.
    #[getter]
    fn residual_dim(&self) -> usize {
        self.compiled.residual_dim()
    }
    /// The definition as compiled, as JSON text (what a server's `factor_types` takes).
    fn definition_json(&self) -> PyResult<String> {
        serde_json::to_string(&self.compiled.definition)
            .map_err(|e| FactordError::new_err(format!("definition: {e}")))
    }
    fn __repr__(&self) -> String {
        let d = &self.compiled.definition;
        let kinds: Vec<String> = d
            .variables
            .iter()
            .map(|v| format!("{}: {}", v.name, v.kind))
            .collect();
        format!("FactorType({}({}))", d.name, kinds.join(", "))
    }
}
