//! Graduated non-convexity (GNC, Yang et al. 2020) over the batch solver: wrong loop closures
//! rejected without a kernel or scale chosen by the user.
//!
//! 1. The plain least-squares solve runs first, exactly as without GNC. When every factor marked
//!    possibly wrong ends within its χ² quantile at 1 − 1e-6 there, nothing looks wrong and that
//!    solve is the answer: a clean file costs one more residual evaluation.
//!    A plain solve still far beyond a consistent chi2 after a few iterations is given up early.
//! 2. Otherwise the graduation starts from the estimate of the trusted factors alone (odometry
//!    and priors: a spanning tree the wrong closures cannot bend), with every candidate weighted
//!    by the surrogate's weight at its error. Each outer step re-estimates the poses by the
//!    chordal relaxation with the weights held (2D orientations unwrapped at the current
//!    estimate, not along a tree that could run through a wrong closure): a linear, global
//!    estimate, so the graduation does not follow the rotations into a local minimum, which
//!    warm-started Gauss-Newton steps did on M3500 (2.9-25 m off). It then recomputes the
//!    errors and weights and moves μ one step. Where no chordal estimate applies, warm-started
//!    Levenberg-Marquardt iterations take its place; all solves share one ordering, layout and
//!    symbolic factorisation (the weights change values, never the sparsity).
//! 3. The decisions are then binary: a full solve with the kept candidates at weight 1 and the
//!    rejected at 0, from the chordal estimate of the kept measurements, ends at their
//!    least-squares optimum; the decisions are taken again there (a candidate within its
//!    threshold is kept) until they stop changing.
//!
//! 4. Where the kept measurements fit far better than their information matrices say (a
//!    variance factor below 0.25), a second round graduates in the measured scale, the
//!    candidates only it rejects are tested cluster by cluster (a cluster that fits itself but
//!    bends the map is one wrong hypothesis), and the round of lower cost in that scale wins
//!    ([`noise_scale`](self::noise_scale)): groups of wrong closures that agree with each other
//!    hide inside thresholds that are too loose.
//!
//! The truncation threshold of a factor with residual dimension d is the χ²(d) quantile at the
//! given confidence, so a measurement is rejected when its error is less likely than
//! `1 − confidence` for a correct one.

mod candidates;
mod estimates;
mod kernel;
mod noise_scale;

pub use candidates::{has_loop_closures, loop_closures};
pub use kernel::GncKernel;

use std::ops::ControlFlow;
use std::time::Instant;

use faer::sparse::linalg::SupernodalThreshold;
use serde::{Deserialize, Serialize};

use super::budget::Budget;
use super::chi_square::cached_quantile;
use super::cholesky::SparseCholesky;
use super::gauge::anchor_components;
use super::iterations::Iterations;
use super::linear::LinearSolver;
use super::linearize::{free_adjacency, SystemLayout};
use super::optimizer::{optimize_within, Context};
use super::options::{Initialization, Method, SolverOptions};
use super::structure::{BlockOrdering, ScalarRows};
use super::summary::{IterationReport, Summary, Termination, TerminationReason, Timings};
use super::SolverError;
use crate::factors::SqrtInformation;
use crate::problem::{Problem, Values};
use crate::variables::Variable;

/// Re-decisions at the kept measurements' optimum at most (each a chordal estimate and a solve).
const MAX_POLISH_ROUNDS: usize = 5;

/// Levenberg-Marquardt iterations per outer step at least where no chordal estimate applies.
const FALLBACK_INNER_ITERATIONS: usize = 3;

/// The χ² quantile a candidate's error must exceed at the plain optimum for graduation to start.
const START_CONFIDENCE: f64 = 1.0 - 1e-6;

/// Plain least-squares iterations before a chi2 far beyond consistency ends the plain solve.
const PLAIN_ITERATIONS_BEFORE_GIVING_UP: usize = 5;

/// What graduated non-convexity is asked for; the defaults need no tuning.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(default, deny_unknown_fields)]
pub struct GncOptions {
    pub kernel: GncKernel,
    /// The χ² quantile a correct measurement's squared whitened error stays under.
    pub confidence: f64,
    /// Outer steps (μ updates) at most.
    #[serde(deserialize_with = "crate::wire_number::usize")]
    pub max_outer_iterations: usize,
    /// Levenberg-Marquardt iterations per outer step after its weighted chordal estimate
    /// (pose graphs); at least 3 where no chordal estimate applies (warm-started).
    #[serde(deserialize_with = "crate::wire_number::usize")]
    pub inner_iterations: usize,
}

impl Default for GncOptions {
    fn default() -> Self {
        Self {
            kernel: GncKernel::Tls,
            confidence: 0.99,
            max_outer_iterations: 100,
            inner_iterations: 0,
        }
    }
}

impl GncOptions {
    /// Checks every field's range; on failure names the field and says why.
    pub fn validate(&self) -> Result<(), (&'static str, String)> {
        if !(self.confidence > 0.5 && self.confidence < 1.0) {
            return Err((
                "confidence",
                format!(
                    "must be between 0.5 and 1 (exclusive), got {}",
                    self.confidence
                ),
            ));
        }
        if self.max_outer_iterations == 0 || self.max_outer_iterations > 10_000 {
            return Err(("max_outer_iterations", "must be between 1 and 10000".into()));
        }
        if self.inner_iterations > 1000 {
            return Err(("inner_iterations", "must be between 0 and 1000".into()));
        }
        Ok(())
    }
}

/// What the graduation decided, for the Summary's reader.
#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct GncReport {
    pub kernel: GncKernel,
    pub confidence: f64,
    /// Factors marked possibly wrong.
    pub candidates: usize,
    /// Whether the graduation ran (`false`: every candidate fit the plain least-squares optimum).
    pub graduated: bool,
    pub outer_iterations: usize,
    /// Indices (in the problem's factor order) of the factors rejected, ascending.
    pub rejected: Vec<usize>,
    /// Their labels (a file's labels name the line).
    pub rejected_labels: Vec<String>,
    /// The plain least-squares solve's final chi2, before any rejection.
    pub least_squares_chi2: f64,
    /// Wall time of the whole robust solve (the plain solve included).
    pub seconds: f64,
}

/// Solves `problem` as [`optimize_within`] does, then, if factors marked in `possibly_wrong`
/// do not fit, rejects them by graduated non-convexity. The problem's factors are left as they
/// were (weights restored); its values are the robust optimum.
pub fn optimize_gnc(
    problem: &mut Problem,
    options: &SolverOptions,
    gnc: &GncOptions,
    possibly_wrong: &[bool],
    on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
    budget: &dyn Budget,
) -> Result<(Summary, GncReport), SolverError> {
    let start = Instant::now();
    let given = problem.values.clone();
    let quantile = |dof| cached_quantile(dof, gnc.confidence);
    let start_quantile = |dof| cached_quantile(dof, gnc.confidence.max(START_CONFIDENCE));
    let candidates: Vec<usize> = (0..problem.factors().len())
        .filter(|&i| possibly_wrong.get(i).copied().unwrap_or(false))
        .collect();
    // A consistent graph's chi2 is about its number of residuals; one still above every
    // factor's χ² quantile summed after a few iterations has wrong measurements, and more
    // iterations of plain least squares on it only cost time (M3500 with 20 % wrong closures:
    // 100 iterations, 3.9 s).
    let hopeless: f64 = if candidates.is_empty() {
        f64::INFINITY
    } else {
        problem
            .factors()
            .iter()
            .map(|f| quantile(f.factor.residual_dim()))
            .sum()
    };
    let (plain, gave_up) = plain_solve(problem, options, hopeless, on_iteration, budget)?;
    let mut report = GncReport {
        kernel: gnc.kernel,
        confidence: gnc.confidence,
        candidates: candidates.len(),
        graduated: false,
        outer_iterations: 0,
        rejected: Vec::new(),
        rejected_labels: Vec::new(),
        least_squares_chi2: plain.final_chi2,
        seconds: 0.0,
    };
    let originals: Vec<SqrtInformation> = candidates
        .iter()
        .map(|&i| problem.factors()[i].sqrt_information.clone())
        .collect();
    let thresholds: Vec<f64> = candidates
        .iter()
        .map(|&i| quantile(problem.factors()[i].factor.residual_dim()))
        .collect();
    // Graduation starts only on an error no correct measurement makes in practice: with the
    // rejection threshold itself, about 1 % of the correct closures of a file whose noise is as
    // its information says would start it and be rejected, moving a clean file's optimum.
    let fits = |problem: &Problem| -> Result<bool, SolverError> {
        let errors = squared_errors(
            problem,
            &problem.values,
            candidates.iter().copied().zip(&originals),
        )?;
        Ok(errors.iter().zip(&candidates).all(|(&s, &i)| {
            let dof = problem.factors()[i].factor.residual_dim();
            s <= start_quantile(dof)
        }))
    };
    if candidates.is_empty()
        || (plain.termination.reason == TerminationReason::Interrupted && !gave_up)
        || (!gave_up && fits(problem)?)
    {
        report.seconds = start.elapsed().as_secs_f64();
        return Ok((plain, report));
    }
    let graduation = Graduation {
        options,
        gnc,
        candidates: &candidates,
        originals: &originals,
        thresholds: &thresholds,
        budget,
    };
    let outcome = graduation.run(problem, given, plain.initial_chi2, start, on_iteration);
    // The weights are the solve's, not the problem's: whatever happened, the factors go back.
    for (&i, sqrt) in candidates.iter().zip(&originals) {
        problem.factors_mut()[i].sqrt_information = sqrt.clone();
    }
    let (summary, outer_iterations, kept) = outcome?;
    report.graduated = true;
    report.outer_iterations = outer_iterations;
    for (&i, keep) in candidates.iter().zip(kept) {
        if !keep {
            report.rejected.push(i);
            report
                .rejected_labels
                .push(problem.factors()[i].label.clone());
        }
    }
    report.seconds = start.elapsed().as_secs_f64();
    Ok((summary, report))
}

/// The plain least-squares solve, given up after a few iterations while chi2 stays above
/// `hopeless` (returns whether it was).
fn plain_solve(
    problem: &mut Problem,
    options: &SolverOptions,
    hopeless: f64,
    on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
    budget: &dyn Budget,
) -> Result<(Summary, bool), SolverError> {
    let mut gave_up = false;
    let plain = optimize_within(
        problem,
        options,
        &mut |report| {
            on_iteration(report)?;
            if report.iteration >= PLAIN_ITERATIONS_BEFORE_GIVING_UP
                && report.chi2.min(report.trial_chi2) > hopeless
            {
                gave_up = true;
                return ControlFlow::Break(());
            }
            ControlFlow::Continue(())
        },
        budget,
    )?;
    Ok((plain, gave_up))
}

/// The graduation's fixed inputs.
struct Graduation<'a> {
    options: &'a SolverOptions,
    gnc: &'a GncOptions,
    candidates: &'a [usize],
    originals: &'a [SqrtInformation],
    thresholds: &'a [f64],
    budget: &'a dyn Budget,
}

impl Graduation<'_> {
    /// The robust solve from the given values; the Summary, the outer steps taken and, per
    /// candidate, whether it is kept. The values end in `problem.values`.
    fn run(
        &self,
        problem: &mut Problem,
        given: Values,
        initial_chi2: f64,
        start: Instant,
        on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
    ) -> Result<(Summary, usize, Vec<bool>), SolverError> {
        let (fixed, gauge_fixed) = anchor_components(problem.factors(), &given);
        let ordering = BlockOrdering::amd(free_adjacency(problem.factors(), &fixed));
        let layout = SystemLayout::with_ordering(
            problem.factors(),
            &given,
            &fixed,
            &ordering,
            ScalarRows::Listed,
        );
        let chol = LinearSolver::Sparse(SparseCholesky::analyze(
            &layout.pattern,
            SupernodalThreshold::FORCE_SUPERNODAL,
        )?);
        let (mut values, initialization) = self.trusted_estimate(problem, given);
        let trusted = values.clone();
        let mut solver = Iterations::new(
            &layout,
            chol,
            Timings::default(),
            &values,
            false,
            self.budget,
        );
        let mut round = self.decide(problem, &mut solver, &mut values, 1.0, on_iteration)?;
        if !round.interrupted {
            round = self.second_round(
                problem,
                &mut solver,
                &mut values,
                trusted,
                layout.pattern.n,
                round,
                on_iteration,
            )?;
        }
        let Decisions {
            chi2,
            termination,
            kept,
            outer,
            ..
        } = round;
        let run = solver.finish(chi2, termination);
        let summary = run.summary(
            self.options,
            &layout,
            problem.factors(),
            &values,
            Context {
                start,
                initialization,
                gauge_fixed,
                initial_chi2,
                initialized_chi2: None,
                region: None,
            },
        );
        problem.values = values;
        Ok((summary, outer, kept))
    }

    /// One graduation from `values` with the thresholds times `noise_scale`, then the polish
    /// (decisions at the unscaled thresholds); the values end at the kept measurements' optimum.
    fn decide(
        &self,
        problem: &mut Problem,
        solver: &mut Iterations,
        values: &mut Values,
        noise_scale: f64,
        on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
    ) -> Result<Decisions, SolverError> {
        let mut ratios = self.ratios(problem, values, noise_scale)?;
        let graduation = self.graduate(
            problem,
            solver,
            values,
            &mut ratios,
            noise_scale,
            on_iteration,
        )?;
        let kept: Vec<bool> = ratios
            .iter()
            .zip(&graduation.weights)
            .map(|(&r, &w)| self.gnc.kernel.keeps(r, w))
            .collect();
        let (chi2, termination, kept) = self.polish(
            problem,
            solver,
            values,
            kept,
            graduation.interrupted,
            on_iteration,
        )?;
        Ok(Decisions {
            chi2,
            interrupted: graduation.interrupted
                || termination.reason == TerminationReason::Interrupted,
            termination,
            kept,
            outer: graduation.outer,
        })
    }

    /// The graduation: μ from convex to the kernel, each step the candidates' weights at the
    /// current residual ratios (`ratios`, updated), then the weighted chordal re-estimate (or,
    /// where it does not apply, warm-started iterations) of `values`.
    fn graduate(
        &self,
        problem: &mut Problem,
        solver: &mut Iterations,
        values: &mut Values,
        ratios: &mut Vec<f64>,
        noise_scale: f64,
        on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
    ) -> Result<GraduationEnd, SolverError> {
        let inner = SolverOptions {
            method: Method::LevenbergMarquardt,
            damp_first_step: true,
            max_iterations: self.gnc.inner_iterations,
            initialization: Initialization::None,
            ..self.options.clone()
        };
        let fallback = SolverOptions {
            max_iterations: self.gnc.inner_iterations.max(FALLBACK_INNER_ITERATIONS),
            ..inner.clone()
        };
        let kernel = self.gnc.kernel;
        let max_ratio = ratios.iter().copied().fold(1.0, f64::max);
        let mut mu = kernel.initial_mu(max_ratio);
        let mut weights = vec![1.0; self.candidates.len()];
        let mut outer = 0;
        while outer < self.gnc.max_outer_iterations {
            outer += 1;
            for (w, &r) in weights.iter_mut().zip(ratios.iter()) {
                *w = kernel.weight(mu, r);
            }
            self.apply(problem, &weights, |w| w);
            let inner = match self.weighted_estimate(problem, values, &weights) {
                Some(estimate) => {
                    *values = estimate;
                    &inner
                }
                None => &fallback,
            };
            let termination = if inner.max_iterations == 0 {
                super::stopping::stopped(0)
            } else {
                solver
                    .run(problem.factors(), values, inner, on_iteration)?
                    .1
            };
            *ratios = self.ratios(problem, values, noise_scale)?;
            if termination.reason == TerminationReason::Interrupted && inner.max_iterations > 0 {
                return Ok(GraduationEnd {
                    outer,
                    interrupted: true,
                    weights,
                });
            }
            if kernel.converged(mu, &weights, 1e-6) {
                break;
            }
            mu = kernel.next_mu(mu);
        }
        Ok(GraduationEnd {
            outer,
            interrupted: false,
            weights,
        })
    }

    /// The least-squares optimum of the measurements `kept`, from their chordal estimate (the
    /// warm-started path can end in a local minimum of the rotations), then the decisions again
    /// at that optimum, until they stop changing. Returns chi2, how the last solve ended, and
    /// the final decisions.
    fn polish(
        &self,
        problem: &mut Problem,
        solver: &mut Iterations,
        values: &mut Values,
        mut kept: Vec<bool>,
        interrupted: bool,
        on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
    ) -> Result<(f64, Termination, Vec<bool>), SolverError> {
        let mut chi2 = 0.0;
        let mut termination = super::stopping::stopped(0);
        for round in 1..=MAX_POLISH_ROUNDS {
            self.apply(problem, &kept, weight_of);
            if interrupted {
                chi2 = super::evaluate_chi2(problem.factors(), values)?;
                break;
            }
            if let Some(estimate) = self.kept_estimate(problem, values, &kept) {
                *values = estimate;
            }
            (chi2, termination) =
                solver.run(problem.factors(), values, self.options, on_iteration)?;
            if termination.reason == TerminationReason::Interrupted {
                break;
            }
            let ratios = self.ratios(problem, values, 1.0)?;
            let decided: Vec<bool> = ratios.iter().map(|&r| r <= 1.0).collect();
            // The last round's decisions stand as solved: decisions taken after it would not be
            // the ones the values are the optimum of.
            if decided == kept || round == MAX_POLISH_ROUNDS {
                break;
            }
            kept = decided;
        }
        Ok((chi2, termination, kept))
    }

    /// Each candidate's squared whitened error at `values` over its threshold times
    /// `noise_scale` (1: the thresholds the information gives).
    fn ratios(
        &self,
        problem: &Problem,
        values: &Values,
        noise_scale: f64,
    ) -> Result<Vec<f64>, SolverError> {
        let errors = squared_errors(
            problem,
            values,
            self.candidates.iter().copied().zip(self.originals),
        )?;
        Ok(errors
            .iter()
            .zip(self.thresholds)
            .map(|(s, t)| s / (t * noise_scale))
            .collect())
    }

    /// Weights the candidates (`weight` of each entry of `per_candidate`).
    fn apply<T: Copy>(
        &self,
        problem: &mut Problem,
        per_candidate: &[T],
        weight: impl Fn(T) -> f64,
    ) {
        let factors = problem.factors_mut();
        for ((&i, sqrt), &w) in self
            .candidates
            .iter()
            .zip(self.originals)
            .zip(per_candidate)
        {
            factors[i].sqrt_information = sqrt.scaled(weight(w));
        }
    }
}

/// A kept candidate's weight 1, a rejected one's 0.
fn weight_of(keep: bool) -> f64 {
    if keep {
        1.0
    } else {
        0.0
    }
}

/// What one graduation and its polish decided.
struct Decisions {
    chi2: f64,
    termination: Termination,
    /// Per candidate, whether it is kept.
    kept: Vec<bool>,
    /// Outer steps taken (over every graduation).
    outer: usize,
    /// Whether the budget stopped it.
    interrupted: bool,
}

/// Where the graduation ended: its outer steps, whether the budget stopped it, the weights.
struct GraduationEnd {
    outer: usize,
    interrupted: bool,
    weights: Vec<f64>,
}

/// The squared whitened errors ‖R e‖² at `values` of the factors in `factors`, each given with
/// the unweighted square-root information that whitens it.
fn squared_errors<'s>(
    problem: &Problem,
    values: &Values,
    factors: impl IntoIterator<Item = (usize, &'s SqrtInformation)>,
) -> Result<Vec<f64>, SolverError> {
    let mut error = Vec::new();
    let mut whitened = Vec::new();
    let mut variables: Vec<&dyn Variable> = Vec::new();
    factors
        .into_iter()
        .map(|(i, sqrt)| {
            let f = &problem.factors()[i];
            let d = f.factor.residual_dim();
            error.resize(d, 0.0);
            whitened.resize(d, 0.0);
            variables.clear();
            variables.extend(f.variables().iter().map(|&v| values.variable(v)));
            f.factor.evaluate(&variables, &mut error, None)?;
            sqrt.whiten_vector(&error, &mut whitened);
            Ok(whitened.iter().map(|v| v * v).sum())
        })
        .collect()
}
