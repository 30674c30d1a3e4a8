//! The second round of graduated non-convexity, for measurements whose information matrices are
//! far more pessimistic than their noise.
//!
//! Truncation thresholds come from the information matrices. Where those say σ is ten times
//! what the measurements show (M3500: variance factor 0.024), a group of wrong closures that
//! agree with each other (perceptual aliasing) can bend the map at less cost than rejecting
//! them: after the bend each fits well within its threshold, and nothing one closure shows
//! gives the group away. What does is the whole map: the bend raises chi2 by 4.1 on M3500, 175
//! times the measured variance factor, where the group's 51 residuals would raise it by about
//! 51 times that factor if they were right.
//!
//! So, when the first round's kept measurements fit far better than their information says:
//! 1. the variance factor is measured, chi2 over the redundancy (residuals minus free
//!    parameters) at the first round's optimum;
//! 2. a second graduation from the trusted estimate, with every threshold in that scale,
//!    decides again (its polish settles at the unscaled thresholds). Tight thresholds also
//!    reject right closures (the big loop of a drifted trajectory, before the graduation has
//!    closed it), so its rejections of what the first round kept are tested:
//! 3. those candidates are clustered (closures whose ends are near each other's in the variable
//!    order, as consecutive frames of one place recognition are), and each cluster is added to
//!    the second round's optimum. Its rise in chi2 (measured scale) splits in two: its own
//!    residuals at the joint optimum, and the bend, what the rest of the map pays to meet them.
//!    Right closures spread the rise over both; a group that agrees with itself but not with
//!    the map fits almost exactly and puts nearly all of it in the bend (M3500: own 0.3-8.5,
//!    bend 61-171 for 10-17 closures; sphere2500's right closures between two rings: own 123,
//!    bend 158 for 36). A cluster comes back when both halves are within the χ² quantile of its
//!    residual count, and the polish settles again;
//! 4. the round whose truncated least-squares cost in the measured scale is lower wins (the
//!    second can end worse where its tight graduation kept a group the first also kept). A
//!    cluster found inconsistent as a whole is one hypothesis, one place recognised wrongly:
//!    rejecting it costs its quantile once, not each member's threshold (at its members'
//!    thresholds, keeping M3500's group of 17 and bending the map was cheaper).

use std::ops::ControlFlow;

use super::{squared_errors, weight_of, Decisions, Graduation};
use crate::problem::{Problem, Values};
use crate::solver::chi_square::cached_quantile;
use crate::solver::iterations::Iterations;
use crate::solver::summary::{IterationReport, TerminationReason};
use crate::solver::union_find::find_root;
use crate::solver::SolverError;

/// A variance factor below this starts the second round.
const PESSIMISTIC_VARIANCE_FACTOR: f64 = 0.25;

/// Redundancy (residuals minus free parameters) needed to measure the variance factor at all.
const MIN_REDUNDANCY: usize = 30;

/// Closures whose ends are at most this far apart in the variable order, at both ends, belong to
/// one cluster.
const CLUSTER_GAP: usize = 3;

/// Disputed clusters tested at most (each a solve); the rest stay rejected as the second round
/// decided.
const MAX_DISPUTED_CLUSTERS: usize = 64;

/// Disputed closures found inconsistent with the map together, and the cost of rejecting them
/// together.
struct Group {
    members: Vec<usize>,
    threshold: f64,
}

impl Graduation<'_> {
    /// The second round where the first's kept measurements fit far better than their
    /// information says; `first` unchanged otherwise. `values` hold the first round's optimum
    /// and end at the returned decisions' optimum; `trusted` is the trusted factors' estimate.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn second_round(
        &self,
        problem: &mut Problem,
        solver: &mut Iterations,
        values: &mut Values,
        trusted: Values,
        free_scalars: usize,
        first: Decisions,
        on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
    ) -> Result<Decisions, SolverError> {
        let Some(scale) = self.variance_factor(problem, &first, free_scalars) else {
            return Ok(first);
        };
        let mut tight_values = trusted;
        let tight = self.decide(problem, solver, &mut tight_values, scale, on_iteration)?;
        let outer = first.outer + tight.outer;
        let first_stands = |problem: &mut Problem, first: Decisions| {
            self.apply(problem, &first.kept, weight_of);
            Ok(Decisions { outer, ..first })
        };
        if tight.interrupted {
            return first_stands(problem, first);
        }
        let disputed: Vec<usize> = (0..first.kept.len())
            .filter(|&c| first.kept[c] && !tight.kept[c])
            .collect();
        let clusters = self.clusters(problem, &disputed);
        let mut kept = tight.kept.clone();
        let mut inconsistent_groups = Vec::new();
        for cluster in clusters.iter().take(MAX_DISPUTED_CLUSTERS) {
            let mut with = tight.kept.clone();
            for &c in cluster {
                with[c] = true;
            }
            self.apply(problem, &with, weight_of);
            let mut trial = tight_values.clone();
            let (chi2, termination) =
                solver.run(problem.factors(), &mut trial, self.options, on_iteration)?;
            if termination.reason == TerminationReason::Interrupted {
                return first_stands(problem, first);
            }
            let (own, threshold) = self.own_cost(problem, &trial, cluster, scale)?;
            let bend = (chi2 - tight.chi2) / scale - own;
            if own <= threshold && bend <= threshold {
                for &c in cluster {
                    kept[c] = true;
                }
            } else {
                inconsistent_groups.push(Group {
                    members: cluster.clone(),
                    threshold,
                });
            }
        }
        let second = if kept == tight.kept {
            self.apply(problem, &tight.kept, weight_of);
            tight
        } else {
            let (chi2, termination, kept) = self.polish(
                problem,
                solver,
                &mut tight_values,
                kept,
                false,
                on_iteration,
            )?;
            Decisions {
                chi2,
                interrupted: termination.reason == TerminationReason::Interrupted,
                termination,
                kept,
                outer,
            }
        };
        let cost = |decisions: &Decisions| self.robust_cost(decisions, scale, &inconsistent_groups);
        if second.interrupted || cost(&second) >= cost(&first) {
            return first_stands(problem, first);
        }
        *values = tight_values;
        Ok(Decisions { outer, ..second })
    }

    /// The chi2 of `cluster`'s members at `values` in the measured scale, and the χ² quantile
    /// of their residual count.
    fn own_cost(
        &self,
        problem: &Problem,
        values: &Values,
        cluster: &[usize],
        scale: f64,
    ) -> Result<(f64, f64), SolverError> {
        let residuals: usize = cluster
            .iter()
            .map(|&c| problem.factors()[self.candidates[c]].factor.residual_dim())
            .sum();
        let members = cluster
            .iter()
            .map(|&c| (self.candidates[c], &self.originals[c]));
        let own: f64 = squared_errors(problem, values, members)?.iter().sum();
        Ok((own / scale, cached_quantile(residuals, self.gnc.confidence)))
    }

    /// The truncated least-squares cost of `decisions` in the measured noise scale: the kept
    /// measurements' chi2 in that scale plus each rejected one's threshold, where a group found
    /// inconsistent as a whole and rejected whole costs its group threshold instead of the sum of
    /// its members' (it is one hypothesis, one place recognised wrongly).
    fn robust_cost(&self, decisions: &Decisions, scale: f64, groups: &[Group]) -> f64 {
        let rejected: f64 = decisions
            .kept
            .iter()
            .zip(self.thresholds)
            .filter(|(&keep, _)| !keep)
            .map(|(_, &threshold)| threshold)
            .sum();
        let grouped: f64 = groups
            .iter()
            .filter(|group| group.members.iter().all(|&c| !decisions.kept[c]))
            .map(|group| {
                let members: f64 = group.members.iter().map(|&c| self.thresholds[c]).sum();
                group.threshold - members
            })
            .sum();
        decisions.chi2 / scale + rejected + grouped
    }

    /// chi2 over the redundancy of the kept measurements at `first`'s optimum, where it is
    /// below [`PESSIMISTIC_VARIANCE_FACTOR`] and the redundancy is enough to measure it.
    fn variance_factor(
        &self,
        problem: &Problem,
        first: &Decisions,
        free_scalars: usize,
    ) -> Option<f64> {
        let rejected_residuals: usize = first
            .kept
            .iter()
            .zip(self.candidates)
            .filter(|(&keep, _)| !keep)
            .map(|(_, &i)| problem.factors()[i].factor.residual_dim())
            .sum();
        let residuals: usize = problem
            .factors()
            .iter()
            .map(|f| f.factor.residual_dim())
            .sum::<usize>()
            - rejected_residuals;
        let redundancy = residuals.checked_sub(free_scalars)?;
        if redundancy < MIN_REDUNDANCY {
            return None;
        }
        let factor = first.chi2 / redundancy as f64;
        (factor > 0.0 && factor < PESSIMISTIC_VARIANCE_FACTOR).then_some(factor)
    }

    /// The candidates `disputed` (indices into the candidates) in clusters of closures whose
    /// ends are near each other's, each cluster ascending, clusters by their first member.
    fn clusters(&self, problem: &Problem, disputed: &[usize]) -> Vec<Vec<usize>> {
        let ends: Vec<(usize, usize)> = disputed
            .iter()
            .map(|&c| {
                let vars = problem.factors()[self.candidates[c]].variables();
                let low = vars.iter().copied().min().unwrap_or(0);
                let high = vars.iter().copied().max().unwrap_or(0);
                (low, high)
            })
            .collect();
        let mut parent: Vec<usize> = (0..disputed.len()).collect();
        for a in 0..disputed.len() {
            for b in a + 1..disputed.len() {
                let near = ends[a].0.abs_diff(ends[b].0) <= CLUSTER_GAP
                    && ends[a].1.abs_diff(ends[b].1) <= CLUSTER_GAP;
                if near {
                    let (ra, rb) = (find_root(&mut parent, a), find_root(&mut parent, b));
                    parent[ra.max(rb)] = ra.min(rb);
                }
            }
        }
        let mut clusters: Vec<Vec<usize>> = Vec::new();
        let mut slot_of_root = vec![usize::MAX; disputed.len()];
        for (a, &c) in disputed.iter().enumerate() {
            let root = find_root(&mut parent, a);
            if slot_of_root[root] == usize::MAX {
                slot_of_root[root] = clusters.len();
                clusters.push(Vec::new());
            }
            clusters[slot_of_root[root]].push(c);
        }
        clusters
    }
}
