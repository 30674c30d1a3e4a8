//! Solves of a problem that grows between them (a session): the elimination order kept across
//! full re-solves, solves of a region with the rest held fixed, and the Newton decrement that
//! tells whether a region was large enough.

use std::ops::ControlFlow;
use std::time::Instant;

use faer::sparse::linalg::SupernodalThreshold;

use super::budget::Budget;
use super::cholesky::SparseCholesky;
use super::linear::LinearSolver;
use super::linearize::{free_adjacency, free_blocks, linearize, Scratch, SystemLayout};
use super::optimizer::{iterate, Context};
use super::options::{Initialization, SolverOptions};
use super::structure::BlockOrdering;
use super::summary::{IterationReport, Summary, Timings};
use super::vector::dot;
use super::SolverError;
use crate::problem::FactorEntry;
use crate::problem::Problem;

/// The elimination order of a problem's last solve, reused while the problem only grows: new
/// variables go to the end of the order (they are usually the newest poses, eliminated last as
/// iSAM does), and a fresh AMD runs once the problem has grown by a quarter since the last one,
/// or when the set of fixed variables changed.
#[derive(Debug, Default)]
pub struct OrderingCache {
    /// Per variable at the last AMD: fixed in the solve or not, and its elimination position.
    fixed: Vec<bool>,
    position: Vec<Option<usize>>,
    variables_at_amd: usize,
}

impl OrderingCache {
    pub(super) fn ordering(&mut self, factors: &[FactorEntry], fixed: &[bool]) -> BlockOrdering {
        let adjacency = free_adjacency(factors, fixed);
        let old = self.fixed.len();
        let reusable = old > 0
            && fixed.len() >= old
            && fixed[..old] == self.fixed[..]
            && 4 * fixed.len() <= 5 * self.variables_at_amd;
        if !reusable {
            let ordering = BlockOrdering::amd(adjacency);
            let (block, _) = free_blocks(fixed.iter().copied());
            self.position = block
                .iter()
                .map(|b| b.map(|b| ordering.position[b]))
                .collect();
            self.fixed = fixed.to_vec();
            self.variables_at_amd = fixed.len();
            return ordering;
        }
        // Old free variables keep their positions; new ones follow in index order.
        let mut next = self.position.iter().flatten().count();
        let mut position = Vec::with_capacity(adjacency.len());
        for (v, &is_fixed) in fixed.iter().enumerate() {
            if is_fixed {
                continue;
            }
            position.push(match self.position.get(v) {
                Some(&Some(p)) => p,
                _ => {
                    next += 1;
                    next - 1
                }
            });
        }
        let mut block_at = vec![0; position.len()];
        for (b, &p) in position.iter().enumerate() {
            block_at[p] = b;
        }
        BlockOrdering {
            adjacency,
            position,
            block_at,
        }
    }
}

/// Optimises only the variables not marked in `fixed` (indexed like `problem.values`), over
/// the factors listed in `factors` (indices into `problem.factors()`): a session re-solving the
/// neighbourhood of an update. Chi2 values in the Summary are those of these factors only. The
/// caller fixes the gauge (the region's boundary, or the problem's anchors). Warm start as
/// [`optimize_warm`](super::optimize_warm).
pub fn optimize_region(
    problem: &mut Problem,
    fixed: &[bool],
    factors: &[usize],
    options: &SolverOptions,
    on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
) -> Result<Summary, SolverError> {
    optimize_region_within(
        problem,
        fixed,
        factors,
        options,
        on_iteration,
        &super::Unlimited,
    )
}

/// [`optimize_region`] within a [`Budget`], as [`super::optimize_within`].
pub fn optimize_region_within(
    problem: &mut Problem,
    fixed: &[bool],
    factors: &[usize],
    options: &SolverOptions,
    on_iteration: &mut dyn FnMut(&IterationReport) -> ControlFlow<()>,
    budget: &dyn Budget,
) -> Result<Summary, SolverError> {
    let start = Instant::now();
    let options = SolverOptions {
        initialization: Initialization::None,
        ..options.clone()
    };
    let mut timings = Timings::default();
    let mut values = std::mem::take(&mut problem.values);
    let all = problem.factors();
    let subset: Vec<&FactorEntry> = factors.iter().map(|&f| &all[f]).collect();
    let result = (|| {
        let initial_chi2 = super::optimizer::initial_chi2(&subset, &values, budget)?;
        if !initial_chi2.is_finite() {
            return Err(SolverError::NonFiniteInitialCost);
        }
        let layout = SystemLayout::new(&subset, &values, fixed);
        let chol = LinearSolver::Sparse(SparseCholesky::analyze(
            &layout.pattern,
            SupernodalThreshold::FORCE_SUPERNODAL,
        )?);
        timings.preprocess_seconds = start.elapsed().as_secs_f64();
        let run = iterate(
            &mut values,
            &subset,
            &layout,
            chol,
            timings,
            &options,
            on_iteration,
            true,
            budget,
        )?;
        let free = layout.var_at.len();
        Ok(run.summary(
            &options,
            &layout,
            &subset,
            &values,
            Context {
                start,
                initialization: "none (warm start)".into(),
                gauge_fixed: Vec::new(),
                initial_chi2,
                initialized_chi2: None,
                region: Some(free),
            },
        ))
    })();
    problem.values = values;
    result
}

/// The chi2 decrease one Gauss-Newton step would bring if only the variables not in `fixed`
/// moved, over the factors listed (indices into `problem.factors()`): `bᵀH⁻¹b` at the current
/// values. A session uses it on the ring of variables just outside a re-solved region to decide
/// whether the region was large enough. Infinite when that system is singular.
pub fn newton_decrement(
    problem: &Problem,
    fixed: &[bool],
    factors: &[usize],
) -> Result<f64, SolverError> {
    let all = problem.factors();
    let subset: Vec<&FactorEntry> = factors.iter().map(|&f| &all[f]).collect();
    let layout = SystemLayout::new(&subset, &problem.values, fixed);
    if layout.n() == 0 {
        return Ok(0.0);
    }
    let mut chol = SparseCholesky::analyze(&layout.pattern, SupernodalThreshold::AUTO)?;
    let mut scratch = Scratch::new(&layout);
    let mut h = vec![0.0; layout.pattern.nnz()];
    let mut b = vec![0.0; layout.n()];
    linearize(
        &subset,
        &problem.values,
        &layout,
        &mut scratch,
        &mut h,
        &mut b,
    )?;
    if chol.factorize(&layout.pattern, &h).is_err() {
        return Ok(f64::INFINITY);
    }
    let mut step = b.clone();
    chol.solve_in_place(&mut step);
    Ok(dot(&step, &b))
}
