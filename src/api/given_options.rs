//! Solver options as a session's creation gives them: any subset of the fields, the others the
//! session kind's defaults. A bundle adjustment created with `{"max_iterations": 20}` keeps
//! Levenberg-Marquardt damped from the first step (its defaults), where filling the rest from
//! the pose graphs' defaults would have switched it to Gauss-Newton, whose system a free gauge
//! makes singular.

use serde::{Deserialize, Serialize};

use crate::solver::{Initialization, LinearSolverChoice, Method, SolverOptions};

/// [`SolverOptions`] with every field optional (a field absent or `null` is the kind's); on the
/// wire (and in the OpenAPI document) the shape of [`SolverOptions`].
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GivenSolverOptions {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub method: Option<Method>,
    #[serde(
        default,
        deserialize_with = "crate::wire_number::optional_u64",
        skip_serializing_if = "Option::is_none"
    )]
    pub max_iterations: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub function_tolerance: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gradient_tolerance: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub parameter_tolerance: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub initial_lambda: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub damp_first_step: Option<bool>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub initial_trust_radius: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub initialization: Option<Initialization>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub linear_solver: Option<LinearSolverChoice>,
    #[serde(
        default,
        deserialize_with = "crate::wire_number::optional_u64",
        skip_serializing_if = "Option::is_none"
    )]
    pub threads: Option<u64>,
}

impl GivenSolverOptions {
    /// The fields given, the others from `defaults` (not validated: see
    /// [`SolverOptions::validate`]).
    pub fn over(&self, defaults: SolverOptions) -> SolverOptions {
        // A count beyond usize is refused by validation as any count out of range.
        let count = |v: u64| usize::try_from(v).unwrap_or(usize::MAX);
        SolverOptions {
            method: self.method.unwrap_or(defaults.method),
            max_iterations: self.max_iterations.map_or(defaults.max_iterations, count),
            function_tolerance: self
                .function_tolerance
                .unwrap_or(defaults.function_tolerance),
            gradient_tolerance: self
                .gradient_tolerance
                .unwrap_or(defaults.gradient_tolerance),
            parameter_tolerance: self
                .parameter_tolerance
                .unwrap_or(defaults.parameter_tolerance),
            initial_lambda: self.initial_lambda.unwrap_or(defaults.initial_lambda),
            damp_first_step: self.damp_first_step.unwrap_or(defaults.damp_first_step),
            initial_trust_radius: self
                .initial_trust_radius
                .unwrap_or(defaults.initial_trust_radius),
            initialization: self.initialization.unwrap_or(defaults.initialization),
            linear_solver: self.linear_solver.unwrap_or(defaults.linear_solver),
            threads: self.threads.map_or(defaults.threads, count),
        }
    }
}

impl From<SolverOptions> for GivenSolverOptions {
    /// All of `options` given: what a session's creation record keeps, so recovery builds the
    /// options it ran with whatever the kind's defaults are by then.
    fn from(options: SolverOptions) -> Self {
        Self {
            method: Some(options.method),
            max_iterations: Some(options.max_iterations as u64),
            function_tolerance: Some(options.function_tolerance),
            gradient_tolerance: Some(options.gradient_tolerance),
            parameter_tolerance: Some(options.parameter_tolerance),
            initial_lambda: Some(options.initial_lambda),
            damp_first_step: Some(options.damp_first_step),
            initial_trust_radius: Some(options.initial_trust_radius),
            initialization: Some(options.initialization),
            linear_solver: Some(options.linear_solver),
            threads: Some(options.threads as u64),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn given_fields_override_the_defaults_and_only_they() {
        let given: GivenSolverOptions =
            serde_json::from_str(r#"{"max_iterations": 20, "threads": null}"#).unwrap();
        let options = given.over(SolverOptions::bundle_adjustment());
        assert_eq!(
            options,
            SolverOptions {
                max_iterations: 20,
                ..SolverOptions::bundle_adjustment()
            }
        );
        let whole = SolverOptions {
            method: Method::Dogleg,
            threads: 2,
            ..SolverOptions::default()
        };
        let all = GivenSolverOptions::from(whole.clone());
        assert_eq!(all.over(SolverOptions::bundle_adjustment()), whole);
        let text = serde_json::to_string(&all).unwrap();
        let back: GivenSolverOptions = serde_json::from_str(&text).unwrap();
        assert_eq!(back, all);
        assert_eq!(
            serde_json::to_string(&GivenSolverOptions::default()).unwrap(),
            "{}"
        );
    }

    #[test]
    fn unknown_fields_and_wrong_types_are_refused() {
        for text in [
            r#"{"max_iteration": 20}"#,
            r#"{"method": "newton"}"#,
            r#"{"max_iterations": "ten"}"#,
            r#"{"max_iterations": 2.5}"#,
        ] {
            assert!(
                serde_json::from_str::<GivenSolverOptions>(text).is_err(),
                "{text}"
            );
        }
        let whole: GivenSolverOptions =
            serde_json::from_str(r#"{"max_iterations": 20.0}"#).unwrap();
        assert_eq!(whole.max_iterations, Some(20));
    }
}
