//! When the iteration loop stops: the convergence tests on an accepted step (function,
//! warm-start model match, parameter tolerance) and the Termination records for every way a
//! solve ends, including the budget stopping it mid-iteration.

use super::options::SolverOptions;
use super::summary::{Termination, TerminationReason};

/// The convergence test after an accepted step from chi2 `previous` to `trial_chi2`, whose model
/// predicted a decrease of `predicted`; `model_match` enables the model-match stop of
/// [`super::optimize_warm`] (a warm solve whose step was the model's minimum, undamped: a damped
/// step the model predicted well can still stop well short of the optimum). `None`: keep
/// iterating.
pub(super) fn accepted_step_stop(
    options: &SolverOptions,
    model_match: bool,
    relative_decrease: f64,
    previous: f64,
    trial_chi2: f64,
    predicted: f64,
    step_norm: f64,
) -> Option<Termination> {
    if options.function_tolerance > 0.0 && relative_decrease.abs() <= options.function_tolerance {
        Some(termination(
            TerminationReason::FunctionTolerance,
            relative_decrease,
            options.function_tolerance,
            &format!(
                "function tolerance reached: relative decrease {relative_decrease:.3e} <= {:.3e}",
                options.function_tolerance
            ),
        ))
    } else if model_match
        && options.function_tolerance > 0.0
        && ((previous - trial_chi2) - predicted).abs() <= options.function_tolerance * trial_chi2
    {
        let mismatch = ((previous - trial_chi2) - predicted).abs() / trial_chi2;
        Some(termination(
            TerminationReason::FunctionTolerance,
            mismatch,
            options.function_tolerance,
            &format!(
                "function tolerance reached: the step's decrease matched the quadratic model to {mismatch:.3e} of chi2 <= {:.3e} (warm start)",
                options.function_tolerance
            ),
        ))
    } else if options.parameter_tolerance > 0.0 && step_norm <= options.parameter_tolerance {
        Some(termination(
            TerminationReason::ParameterTolerance,
            step_norm,
            options.parameter_tolerance,
            &format!(
                "parameter tolerance reached: |dx|inf = {step_norm:.3e} <= {:.3e}",
                options.parameter_tolerance
            ),
        ))
    } else {
        None
    }
}

/// The solve's budget stopped it inside iteration `iteration` (0: before the first).
pub(super) fn stopped(iteration: usize) -> Termination {
    termination(
        TerminationReason::Interrupted,
        iteration as f64,
        0.0,
        &format!("interrupted by the solve's budget (time limit, cancellation or shutdown) during iteration {iteration}; the estimate is the last accepted step"),
    )
}

/// The gradient test before each iteration: the solve ends when |g|∞ is within the tolerance.
pub(super) fn gradient_stop(options: &SolverOptions, gradient: f64) -> Option<Termination> {
    (options.gradient_tolerance > 0.0 && gradient <= options.gradient_tolerance).then(|| {
        termination(
            TerminationReason::GradientTolerance,
            gradient,
            options.gradient_tolerance,
            &format!(
                "gradient tolerance reached: |g|inf = {gradient:.3e} <= {:.3e}",
                options.gradient_tolerance
            ),
        )
    })
}

/// The caller's `on_iteration` stopped the solve after iteration `iteration`.
pub(super) fn interrupted_by_caller(iteration: usize) -> Termination {
    termination(
        TerminationReason::Interrupted,
        iteration as f64,
        0.0,
        "interrupted by the caller after this iteration",
    )
}

/// Every iteration `options` allows ran without another stop.
pub(super) fn max_iterations(options: &SolverOptions) -> Termination {
    let n = options.max_iterations as f64;
    termination(
        TerminationReason::MaxIterations,
        n,
        n,
        &format!(
            "maximum number of iterations reached ({})",
            options.max_iterations
        ),
    )
}

pub(super) fn termination(
    reason: TerminationReason,
    value: f64,
    threshold: f64,
    message: &str,
) -> Termination {
    Termination {
        reason,
        value,
        threshold,
        message: message.to_string(),
    }
}
