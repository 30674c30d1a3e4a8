//! The chordal estimates the graduation starts from and re-estimates with: of the trusted
//! factors alone, of the factors at their current weights, of the measurements kept.

use std::cell::Cell;

use super::Graduation;
use crate::problem::{FactorEntry, Problem, Values};
use crate::solver::gauge::anchor_components;
use crate::solver::initialize::{chordal, chordal_unwrapped_at_values, Stoppable};
use crate::solver::linearize::free_adjacency;
use crate::solver::structure::BlockOrdering;

/// How a chordal estimate unwraps 2D orientations.
enum Unwrap {
    /// Along a spanning tree of the factors used.
    AlongTree,
    /// At the given values (the graduation's current estimate: a tree could run through a
    /// wrong closure).
    AtValues,
}

impl Graduation<'_> {
    /// The estimate of the trusted factors alone (chordal over odometry and priors), which wrong
    /// closures cannot corrupt; the given values where that estimate does not apply.
    pub(super) fn trusted_estimate(&self, problem: &Problem, given: Values) -> (Values, String) {
        let trusted = self.used_factors(problem, &vec![false; self.candidates.len()]);
        match self.chordal_estimate(&trusted, &given, Unwrap::AlongTree) {
            Some(estimate) => (
                estimate,
                "chordal over the trusted factors (graduated non-convexity)".into(),
            ),
            None => (
                given,
                "given values (graduated non-convexity; no chordal estimate)".into(),
            ),
        }
    }

    /// The chordal estimate of the factors at their current weights (candidates of weight 0
    /// left out), unwrapped at `values`; `None` where it does not apply.
    pub(super) fn weighted_estimate(
        &self,
        problem: &Problem,
        values: &Values,
        weights: &[f64],
    ) -> Option<Values> {
        let kept: Vec<bool> = weights.iter().map(|&w| w > 0.0).collect();
        self.chordal_estimate(&self.used_factors(problem, &kept), values, Unwrap::AtValues)
    }

    /// The chordal estimate of the trusted factors and the candidates in `kept`, anchored as
    /// `values` are; `None` where it does not apply.
    pub(super) fn kept_estimate(
        &self,
        problem: &Problem,
        values: &Values,
        kept: &[bool],
    ) -> Option<Values> {
        self.chordal_estimate(&self.used_factors(problem, kept), values, Unwrap::AlongTree)
    }

    /// The trusted factors and the candidates in `kept`, in the problem's order.
    fn used_factors<'p>(&self, problem: &'p Problem, kept: &[bool]) -> Vec<&'p FactorEntry> {
        let mut used: Vec<&FactorEntry> = Vec::with_capacity(problem.factors().len());
        let mut next = self.candidates.iter().zip(kept).peekable();
        for (i, f) in problem.factors().iter().enumerate() {
            match next.peek() {
                Some((&c, &keep)) if c == i => {
                    next.next();
                    if keep {
                        used.push(f);
                    }
                }
                _ => used.push(f),
            }
        }
        used
    }

    /// The chordal estimate over `used`, anchored as `values` are, stoppable by the budget.
    fn chordal_estimate(
        &self,
        used: &[&FactorEntry],
        values: &Values,
        unwrap: Unwrap,
    ) -> Option<Values> {
        let (fixed, _) = anchor_components(used, values);
        let ordering = BlockOrdering::amd(free_adjacency(used, &fixed));
        let stopped = Cell::new(false);
        let stoppable = Stoppable {
            budget: self.budget,
            stopped: &stopped,
        };
        match unwrap {
            Unwrap::AlongTree => chordal(used, values, &fixed, &ordering, None, &stoppable),
            Unwrap::AtValues => {
                chordal_unwrapped_at_values(used, values, &fixed, &ordering, &stoppable)
            }
        }
    }
}
