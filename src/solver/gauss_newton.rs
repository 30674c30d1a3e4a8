//! Gauss-Newton steps: Δ = H⁻¹b at each point, and near the optimum a chord step that reuses the
//! previous point's factorisation. A Gauss-Newton trial is accepted whatever its chi2 (the method
//! has no safeguard of its own), except a chord step that made things worse: that one is
//! discarded and the next iteration factorises at the current point.

use std::borrow::Borrow;
use std::ops::ControlFlow;

use super::iterations::{Iterations, StepTimes};
use super::options::SolverOptions;
use super::strategy::Proposal;
use super::vector::dot;
use super::SolverError;
use crate::problem::{FactorEntry, Values};

/// A chord step is tried only after a step that lowered chi2 by less than this fraction:
/// Gauss-Newton is then in its fast local phase and H barely changes. After larger steps the
/// old factorisation was never good enough on the graphs measured (M3500's first step: 21%),
/// and trying it costs a solve.
const CHORD_AFTER_DECREASE: f64 = 0.1;

#[derive(Default)]
pub(super) struct GaussNewton {
    /// The factorisation in hand is of the last point's H, whose (fresh) step was accepted.
    chord_allowed: bool,
    /// This iteration's step reuses the last factorisation.
    chord: bool,
}

impl GaussNewton {
    pub(super) fn compute_step<E: Borrow<FactorEntry> + Sync>(
        &mut self,
        it: &mut Iterations<'_>,
        factors: &[E],
        values: &Values,
        chi2: f64,
        options: &SolverOptions,
        times: &mut StepTimes,
    ) -> Result<ControlFlow<(), Proposal>, SolverError> {
        self.chord = self.chord_allowed && chord_step(it, options, chi2, times);
        if !self.chord {
            if it.hessian_stale && it.linearize_at(factors, values, times)?.is_break() {
                return Ok(ControlFlow::Break(()));
            }
            let solved = it
                .solve_damped(0.0, times)
                .map_err(|e| it.indeterminate(values, e))?;
            if solved.is_break() {
                return Ok(ControlFlow::Break(()));
            }
        }
        Ok(ControlFlow::Continue(Proposal::Step {
            predicted: dot(&it.delta, &it.b),
            // A chord step solves with the previous point's H: not this point's model minimum.
            undamped: !self.chord,
        }))
    }

    pub(super) fn judge(
        &mut self,
        chi2: f64,
        trial: f64,
        iteration: usize,
    ) -> Result<bool, SolverError> {
        // Not at most chi2 (NaN included).
        let worse = !matches!(
            trial.partial_cmp(&chi2),
            Some(std::cmp::Ordering::Less | std::cmp::Ordering::Equal)
        );
        if self.chord && worse {
            // The old factorisation was not good enough here: discard the step, and factorise
            // at this point next.
            Ok(false)
        } else if !trial.is_finite() {
            Err(SolverError::Diverged { iteration })
        } else {
            Ok(true)
        }
    }

    /// Whether the next iteration may try a chord step (then the new point needs only its
    /// gradient; H follows if the chord step is not taken after all).
    pub(super) fn step_done(
        &mut self,
        accepted: bool,
        relative_decrease: f64,
        warm: bool,
        options: &SolverOptions,
    ) -> bool {
        self.chord_allowed = accepted
            && !self.chord
            && !warm
            && options.function_tolerance > 0.0
            && relative_decrease > 0.0
            && relative_decrease < CHORD_AFTER_DECREASE;
        self.chord_allowed
    }
}

/// A Gauss-Newton step at the current point with the previous point's factorisation (a chord
/// step): `delta = H_prev⁻¹ b`. Worth taking instead of a fresh factorisation when its predicted
/// decrease `deltaᵀb` is already within the function tolerance of `chi2`: the solve is then about
/// to stop, and that step only has to be small and downhill, which the trial evaluation checks
/// (the stopping test is still on the actual decrease). Returns whether `delta` holds such a
/// step; near the optimum H barely changes between iterations, so this saves the last
/// factorisation of a solve.
fn chord_step(
    it: &mut Iterations<'_>,
    options: &SolverOptions,
    chi2: f64,
    times: &mut StepTimes,
) -> bool {
    it.solve_with_factor(times);
    let predicted = dot(&it.delta, &it.b);
    predicted >= 0.0 && predicted <= options.function_tolerance * chi2
}
