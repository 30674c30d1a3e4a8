//! One refactorisation round of an update: the touched columns and their ancestors are
//! ordered again (while the factors whose linearisation point moved are linearised again beside
//! it), refactored from the linearised factors, and solved by forward and back substitution.

use std::time::Instant;

use super::block_factor::{Accumulator, Solution};
use super::{beside, linearized, ordering};
use super::{IncrementalEngine, UpdateParams, UpdateReport, LINEARIZE_BESIDE_FROM};
use crate::problem::Problem;
use crate::solver::SolverError;

impl IncrementalEngine {
    /// One round: refactor the touched variables and their ancestors, then solve.
    pub(super) fn solve_pass(
        &mut self,
        problem: &Problem,
        touched: &mut Vec<usize>,
        params: &UpdateParams,
        report: &mut UpdateReport,
        changed: &mut Vec<usize>,
    ) -> Result<(), SolverError> {
        let affected = self.mark_with_ancestors(touched);
        touched.clear();
        let plan = self.order_and_relinearize(problem, &affected, report)?;
        self.refactor(problem, &plan, report)?;
        self.refactor_flops = plan
            .order
            .iter()
            .map(|&r| self.factor.elimination_flops(r))
            .sum();
        self.update_flops = 0.0;
        self.resolve(problem, &plan.order, params, report, changed);
        report.refactored_columns += affected.len();
        report.reused_subtrees += plan.kept_roots.len();
        for &v in &affected {
            self.mark[v] = false;
        }
        Ok(())
    }

    /// Marks `touched` and every ancestor of theirs in the elimination tree (the columns a
    /// refactorisation must redo); returns them.
    fn mark_with_ancestors(&mut self, touched: &[usize]) -> Vec<usize> {
        let mut affected = Vec::new();
        for &v in touched {
            let mut u = v;
            while !self.mark[u] {
                self.mark[u] = true;
                affected.push(u);
                match self.factor.parent(u) {
                    Some(p) => u = p,
                    None => break,
                }
            }
        }
        affected
    }

    /// Orders the marked columns and, meanwhile, linearises again the factors whose
    /// linearisation point moved (`pending`).
    fn order_and_relinearize(
        &mut self,
        problem: &Problem,
        affected: &[usize],
        report: &mut UpdateReport,
    ) -> Result<RefactorPlan, SolverError> {
        let start = Instant::now();
        let entries = problem.factors();
        // The roots of the kept subtrees hanging off the refactored part: a deeper column's rows
        // in it are a subset of its subtree root's (a column's structure, less its parent, is
        // within its parent's), so their cliques carry all the fill the ordering must see, and
        // only their parents can change.
        let mut order_part = || {
            let mark = &self.mark;
            let reaching = self.factor.reaching(affected, mark);
            let kept_roots: Vec<usize> = reaching
                .iter()
                .copied()
                .filter(|&k| self.factor.parent(k).is_some_and(|p| mark[p]))
                .collect();
            let cliques: Vec<Vec<usize>> = kept_roots
                .iter()
                .map(|&k| self.factor.rows_of(k).filter(|&u| mark[u]).collect())
                .filter(|c: &Vec<usize>| c.len() > 1)
                .collect();
            let by_variable = &self.by_variable;
            let order = ordering::order_affected(
                affected,
                |v, out| {
                    for &f in &by_variable[v] {
                        out.extend(
                            entries[f as usize]
                                .variables()
                                .iter()
                                .filter(|&&u| u != v && mark[u]),
                        );
                    }
                },
                &cliques,
                &self.last,
                &self.dims,
                &mut self.local,
                &mut self.trials,
            );
            let plan = RefactorPlan {
                order,
                reaching,
                kept_roots,
            };
            (plan, start.elapsed())
        };
        // The factors whose linearisation point moved are linearised again meanwhile: the
        // ordering reads only the structure. Many of them (a loop closure's correction) take a
        // second thread, which a streaming client's server has idle while its update runs.
        let pending = std::mem::take(&mut self.pending);
        let mut linearize_part = || {
            let start = Instant::now();
            let change = linearized::relinearize_factors(
                &pending,
                entries,
                &self.theta,
                &mut self.scratch,
                &mut self.linearized,
            );
            (change, start.elapsed())
        };
        let ((plan, order_time), (change, linearize_time)) =
            if pending.len() >= LINEARIZE_BESIDE_FROM {
                beside::run_beside(order_part, linearize_part)
            } else {
                let linearized = linearize_part();
                (order_part(), linearized)
            };
        self.residual_chi2 += change?;
        report.linearize_seconds += linearize_time.as_secs_f64();
        report.order_seconds += order_time.as_secs_f64();
        Ok(plan)
    }

    /// Refactors the columns of `plan.order` from the linearised factors (the kept subtrees'
    /// updates withdrawn first and their roots hung under their new parents).
    fn refactor(
        &mut self,
        problem: &Problem,
        plan: &RefactorPlan,
        report: &mut UpdateReport,
    ) -> Result<(), SolverError> {
        let start = Instant::now();
        let entries = problem.factors();
        self.factor
            .withdraw(&plan.order, &self.offset, &self.y, &mut self.partial);
        let dense_before = self.factor.dense_columns();
        let (linearized, free, dims) = (&self.linearized, &self.free, &self.dims);
        let by_variable = &self.by_variable;
        let assemble = |r: usize, rank: &[u64], acc: &mut Accumulator| {
            let dr = dims[r];
            for &f in &by_variable[r] {
                let (lin, vars) = (&linearized[f as usize], entries[f as usize].variables());
                let Some(i) = vars.iter().position(|&v| v == r) else {
                    continue;
                };
                let cols = lin.cols();
                let ci = lin.col_offset[i];
                add_block(acc.diagonal_mut(), &lin.gram, cols, (ci, ci), (dr, dr));
                for (j, &u) in vars.iter().enumerate() {
                    if j != i && free[u] && rank[u] > rank[r] {
                        let du = dims[u];
                        let block = acc.block_mut(u, du);
                        add_block(block, &lin.gram, cols, (lin.col_offset[j], ci), (du, dr));
                    }
                }
            }
        };
        self.factor
            .refactor(&plan.order, &self.mark, &plan.reaching, assemble)
            .map_err(|e| SolverError::IndeterminateSystem {
                keys: vec![problem.values.key(e.0)],
            })?;
        self.factor.reparent(&plan.kept_roots);
        report.dense_columns += self.factor.dense_columns() - dense_before;
        report.factorize_seconds += start.elapsed().as_secs_f64();
        Ok(())
    }

    /// Forward substitution of the columns of `order` (in that order; every other column keeps
    /// its `y`), then back substitution from the root into what moved. `mark` holds `order`.
    pub(super) fn resolve(
        &mut self,
        problem: &Problem,
        order: &[usize],
        params: &UpdateParams,
        report: &mut UpdateReport,
        changed: &mut Vec<usize>,
    ) {
        let start = Instant::now();
        let entries = problem.factors();
        for &r in order {
            let (o, d) = (self.offset[r], self.dims[r]);
            self.yty -= self.y[o..o + d].iter().map(|v| v * v).sum::<f64>();
        }
        let (linearized, by_variable) = (&self.linearized, &self.by_variable);
        self.factor.forward(
            order,
            &self.offset,
            &mut self.y,
            &mut self.partial,
            |r, out| {
                for &f in &by_variable[r] {
                    let (lin, vars) = (&linearized[f as usize], entries[f as usize].variables());
                    if let Some(i) = vars.iter().position(|&v| v == r) {
                        let c = lin.col_offset[i];
                        for (o, g) in out.iter_mut().zip(&lin.gradient[c..]) {
                            *o -= g;
                        }
                    }
                }
            },
        );
        for &r in order {
            let (o, d) = (self.offset[r], self.dims[r]);
            self.yty += self.y[o..o + d].iter().map(|v| v * v).sum::<f64>();
        }
        let first_changed = changed.len();
        report.solved_columns += self.factor.back_substitute(
            &self.mark,
            &self.offset,
            &self.y,
            Solution {
                x: &mut self.delta,
                propagated: &mut self.propagated,
            },
            params.wildfire_threshold,
            changed,
        );
        for &v in &changed[first_changed..] {
            let (o, d) = (self.offset[v], self.dims[v]);
            self.step[v] = self.delta[o..o + d]
                .iter()
                .fold(0.0f64, |m, s| m.max(s.abs()));
        }
        report.solve_seconds += start.elapsed().as_secs_f64();
    }
}

/// What a refactorisation redoes: the marked columns in elimination order, the kept columns
/// that reach them, and the roots of the kept subtrees hanging off them.
struct RefactorPlan {
    order: Vec<usize>,
    reaching: Vec<usize>,
    kept_roots: Vec<usize>,
}

/// `dst (rows × cols of the block) += gram[origin..]` for a block of a factor's Gram matrix
/// (`stride` columns, row-major).
pub(super) fn add_block(
    dst: &mut [f64],
    gram: &[f64],
    stride: usize,
    (row0, col0): (usize, usize),
    (rows, cols): (usize, usize),
) {
    for i in 0..rows {
        let source = &gram[(row0 + i) * stride + col0..(row0 + i) * stride + col0 + cols];
        for (d, s) in dst[i * cols..(i + 1) * cols].iter_mut().zip(source) {
            *d += s;
        }
    }
}
