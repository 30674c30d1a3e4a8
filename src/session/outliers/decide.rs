//! The two deciders (see the module documentation): the gate on a streamed solve, and
//! consolidation by graduated non-convexity on a full one.

use std::collections::BTreeSet;
use std::ops::ControlFlow;

use super::{DecidedBy, Decision, OutlierOutcome, OutlierWork};
use crate::api::wire::FactorId;
use crate::problem::{FactorEntry, Problem};
use crate::session::incremental::IncrementalSolver;
use crate::session::prepared::PreparedFactor;
use crate::solver::chi_square::cached_quantile;
use crate::solver::{self, GncOptions, IterationReport, SolverError, SolverOptions, Summary};

/// A candidate passes the gate while its distance is within the χ² quantile of its residual's
/// dimension at this confidence: the confidence at which batch graduated non-convexity starts
/// (`solver::gnc`), so the gate holds out only what that would act on.
pub(crate) const GATE_CONFIDENCE: f64 = 1.0 - 1e-6;

/// What the gate let in (appended to the problem, in this order) and decided.
pub(crate) struct GateOutcome {
    pub entered: Vec<FactorId>,
    pub outcome: OutlierOutcome,
}

/// Below this many degrees of freedom (residuals minus free parameters) the problem's own noise
/// scale is not estimated: the information matrices are taken as they are.
const MIN_DOF_FOR_SCALE: usize = 100;

/// The smallest noise scale the gate assumes (a noise-free simulation would otherwise refuse
/// any closure with a rounding error).
const MIN_NOISE_SCALE: f64 = 1e-2;

/// The noise scale the accepted factors show: the variance factor `σ̂₀² = χ² / dof` (geodesy's
/// a-posteriori variance of unit weight), at most 1. Datasets often state their noise
/// pessimistically (M3500's residuals are 6 × smaller than its information says: σ̂₀² =
/// 0.024), and the estimate's covariance `P` then is as much too wide: a wrong closure between
/// poses far apart along the path fits within it. Measured in the noise the data shows, it does
/// not. Never above 1: a map bent by a wrong closure shows large residuals, and trusting those
/// would let more wrong closures in.
pub(crate) fn noise_scale(chi2: f64, residuals: usize, parameters: usize) -> f64 {
    let dof = residuals.saturating_sub(parameters);
    if dof < MIN_DOF_FOR_SCALE || !chi2.is_finite() {
        return 1.0;
    }
    (chi2 / dof as f64).clamp(MIN_NOISE_SCALE, 1.0)
}

/// Weighs each held candidate alone against the engine's estimate, in the noise scale `scale`
/// ([`noise_scale`]); those within the gate are appended to `problem` (the caller's engine
/// update takes them in).
pub(crate) fn gate(
    problem: &mut Problem,
    index: &IncrementalSolver,
    held: Vec<(FactorId, PreparedFactor)>,
    scale: f64,
) -> GateOutcome {
    let mut gated = GateOutcome {
        entered: Vec::new(),
        outcome: OutlierOutcome::default(),
    };
    for (id, f) in held {
        let entry = detach(problem, f);
        let Some(distance) = index.innovation(problem, &entry).map(|d2| d2 / scale) else {
            // A variable the engine has not taken in yet (or no engine): the next solve decides.
            gated.outcome.held.push((id, prepared(entry)));
            continue;
        };
        let accepted = distance <= cached_quantile(entry.factor.residual_dim(), GATE_CONFIDENCE);
        gated.outcome.decisions.push(Decision {
            id,
            accepted,
            distance: Some(distance),
            by: DecidedBy::Gate,
        });
        if accepted {
            problem.push_entry(entry);
            gated.entered.push(id);
        } else {
            gated.outcome.held.push((id, prepared(entry)));
        }
    }
    gated
}

/// Every candidate, accepted and held, decided again together: graduated non-convexity over
/// the whole problem. `factor_ids` are the problem's factors' ids, kept in step as candidates
/// enter and leave. An interrupted solve (budget, preemption) decides nothing: the held
/// candidates leave the problem again as they came.
pub(crate) fn consolidate(
    problem: &mut Problem,
    factor_ids: &mut Vec<FactorId>,
    work: OutlierWork,
    options: &SolverOptions,
    on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
    budget: &dyn solver::Budget,
) -> (Result<Summary, SolverError>, OutlierOutcome) {
    let first = problem.factors().len();
    for (id, f) in work.held {
        let entry = detach(problem, f);
        problem.push_entry(entry);
        factor_ids.push(id);
    }
    let candidates: Vec<bool> = factor_ids
        .iter()
        .enumerate()
        .map(|(i, id)| i >= first || work.accepted.contains(id))
        .collect();
    let solved = solver::optimize_gnc(
        problem,
        options,
        &GncOptions::default(),
        &candidates,
        on_iteration,
        budget,
    );
    let mut outcome = OutlierOutcome::default();
    let rejected: BTreeSet<usize> = match &solved {
        Ok((summary, report))
            if summary.termination.reason != solver::TerminationReason::Interrupted =>
        {
            for (i, _) in candidates.iter().enumerate().filter(|(_, &c)| c) {
                let accepted = report.rejected.binary_search(&i).is_err();
                outcome.decisions.push(Decision {
                    id: factor_ids[i],
                    accepted,
                    distance: None,
                    by: DecidedBy::GraduatedNonConvexity,
                });
            }
            report.rejected.iter().copied().collect()
        }
        // Undecided: what was held goes back to being held.
        _ => (first..factor_ids.len()).collect(),
    };
    let taken = problem.take_factors(|i| rejected.contains(&i));
    let mut taken_ids = Vec::with_capacity(taken.len());
    let mut position = 0;
    factor_ids.retain(|&id| {
        position += 1;
        let leaves = rejected.contains(&(position - 1));
        if leaves {
            taken_ids.push(id);
        }
        !leaves
    });
    outcome.held = taken_ids
        .into_iter()
        .zip(taken)
        .map(|(id, entry)| (id, prepared(entry)))
        .collect();
    (solved.map(|(summary, _)| summary), outcome)
}

fn detach(problem: &Problem, f: PreparedFactor) -> FactorEntry {
    problem
        .detached_entry(f.factor, f.sqrt_information, f.robust, String::new())
        // Its variables were checked when its batch was accepted, and variables never leave.
        .expect("a candidate's variables are in the problem")
}

fn prepared(entry: FactorEntry) -> PreparedFactor {
    PreparedFactor {
        factor: entry.factor,
        sqrt_information: entry.sqrt_information,
        robust: entry.robust,
        candidate: true,
    }
}
