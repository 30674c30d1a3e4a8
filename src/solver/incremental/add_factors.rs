//! An update that only adds factors (nothing relinearised): the factors are added to the kept
//! factor by a rank update along their elimination-tree paths (`block_factor::rank_update`)
//! instead of eliminating and reordering those paths again.
//!
//! Each factor's rows `W` come from its Gram matrix: `G = Q Λ Qᵀ`, `W = Λ^½ Qᵀ` over the
//! eigenvalues it has (a 2D odometry factor's 6×6 Gram has rank 3), so `WᵀW = G`; the
//! right-hand side is not rotated along, the path is solved forward again from the
//! gradients, as after a refactor.
//!
//! The update keeps the order, so fill accumulates where a refactor would have reordered (the
//! newest variables stay on top of the path to every loop closure). Ski-rental amortisation
//! decides: once the rank updates since the last refactoring pass have cost as many flops as
//! that pass, the next update refactors (and reorders) its paths instead. Updates that
//! relinearise refactor anyway. Taking a relinearised factor's change in by an update of its
//! positive part and a hyperbolic downdate of its negative part was measured slower than
//! refactoring (10k stream: 52.9 s of engine time against 50.4 s; the 100k graph's window at
//! 36k poses: 24.4 s against 20.6 s): such a change brings up to six rows per factor, and
//! the fill it keeps makes the next updates dearer (BENCHMARKS.md).

use std::time::Instant;

use nalgebra::{DMatrix, SymmetricEigen};

use super::block_factor::{rank_update_flops, UpdateRows};
use super::refactor_pass::add_block;
use super::{IncrementalEngine, UpdateParams, UpdateReport};
use crate::problem::{FactorEntry, Problem};
use crate::solver::schur::small_cholesky;
use crate::solver::SolverError;

/// A rank update is taken when it costs this many times fewer flops than eliminating its path
/// again (an update's flops cost more time than a refactor's dense kernels, and it keeps fill).
const UPDATE_COST_MARGIN: f64 = 4.0;
/// Below this many flops either way is cheap, and the rank update saves the reordering.
const SMALL_PATH_FLOPS: f64 = 1e5;
/// A factor's Gram eigenvalues below this fraction of its largest are rank it does not have.
const RANK_TOLERANCE: f64 = 1e-12;

impl IncrementalEngine {
    /// Adds the factors from `first_new` on (and the variables from `first_variable` on) by a
    /// rank update and solves, when that applies; `false` (nothing done) when the caller must
    /// refactor: the amortisation says so, a new variable's factors do not determine it on
    /// their own, or the update would not cost clearly less than the refactor.
    pub(super) fn add_factors(
        &mut self,
        problem: &Problem,
        first_new: usize,
        first_variable: usize,
        params: &UpdateParams,
        report: &mut UpdateReport,
        changed: &mut Vec<usize>,
    ) -> Result<bool, SolverError> {
        if self.update_flops >= self.refactor_flops {
            return Ok(false);
        }
        let new: Vec<usize> = (first_variable..self.theta.len())
            .filter(|&v| self.free[v])
            .collect();
        let entries = problem.factors();
        if !new.iter().all(|&v| self.determined(v, entries)) {
            return Ok(false);
        }
        let start = Instant::now();
        let groups: Vec<UpdateRows> = (first_new..entries.len())
            .filter_map(|f| self.factor_rows(f, entries[f].variables()))
            .collect();
        if !self.cheaper_than_refactoring(&groups) {
            return Ok(false);
        }
        self.factor.append(&new);
        let update = self
            .factor
            .add_rows(groups, &self.offset, &self.y, &mut self.partial)
            .map_err(|e| SolverError::IndeterminateSystem {
                keys: vec![problem.values.key(e.0)],
            })?;
        self.update_flops += update.flops;
        report.factorize_seconds += start.elapsed().as_secs_f64();
        for &c in &update.path {
            self.mark[c] = true;
        }
        self.resolve(problem, &update.path, params, report, changed);
        for &c in &update.path {
            self.mark[c] = false;
        }
        report.updated_columns += update.path.len();
        Ok(true)
    }

    /// Whether adding `groups` by a rank update costs clearly less than eliminating their
    /// paths again as they stand (`4·k·d·(d + s)` against `d·s·(s + d)` flops per column of `s`
    /// scalar rows, `k` rows of `W` in all), or both are small. Where a column reaches few
    /// scalars (a 3D map's ring, whose 6-dim factors bring `k = 6` rows each), the update
    /// saves little and keeps the fill a reorder would shed: sphere2500 in-process took 40.8 s
    /// with rank updates wherever the amortisation allowed, 38.1 s without, 33.7 s with this.
    fn cheaper_than_refactoring(&mut self, groups: &[UpdateRows]) -> bool {
        let k: usize = groups.iter().map(|g| g.k).sum();
        let mut path = Vec::new();
        for g in groups {
            for &v in &g.variables {
                let mut u = Some(v as usize);
                while let Some(c) = u.filter(|&c| !self.mark[c]) {
                    self.mark[c] = true;
                    path.push(c);
                    u = self.factor.parent(c);
                }
            }
        }
        let (mut by_update, mut by_refactor) = (0.0, 0.0);
        for &c in &path {
            self.mark[c] = false;
            let (d, s) = (self.dims[c], self.factor.scalar_rows(c));
            by_update += rank_update_flops(k, d, s);
            by_refactor += self.factor.elimination_flops(c);
        }
        UPDATE_COST_MARGIN * by_update <= by_refactor + SMALL_PATH_FLOPS
    }

    /// Whether the factors of `v` (a new variable: all of them new) give it a positive definite
    /// block of its own, so its new column has a pivot whatever the rest.
    fn determined(&self, v: usize, entries: &[FactorEntry]) -> bool {
        let d = self.dims[v];
        let mut block = vec![0.0; d * d];
        for &f in &self.by_variable[v] {
            let lin = &self.linearized[f as usize];
            let vars = entries[f as usize].variables();
            let Some(i) = vars.iter().position(|&u| u == v) else {
                continue;
            };
            let c = lin.col_offset[i];
            add_block(&mut block, &lin.gram, lin.cols(), (c, c), (d, d));
        }
        small_cholesky(&mut block, d).is_ok()
    }

    /// Rows `W` with `WᵀW` the Gram of factor `f` (over its variables `vars`) restricted to its
    /// free variables; `None` for a factor without any (or without information).
    fn factor_rows(&self, f: usize, vars: &[usize]) -> Option<UpdateRows> {
        let lin = &self.linearized[f];
        let mut columns = Vec::new();
        let mut variables = Vec::new();
        for (i, &v) in vars.iter().enumerate() {
            if self.free[v] {
                variables.push(v as u32);
                columns.extend(lin.col_offset[i]..lin.col_offset[i] + self.dims[v]);
            }
        }
        let m = columns.len();
        if m == 0 {
            return None;
        }
        let cols = lin.cols();
        let gram = DMatrix::from_fn(m, m, |a, b| lin.gram[columns[a] * cols + columns[b]]);
        let eigen = SymmetricEigen::new(gram);
        let largest = eigen.eigenvalues.max();
        if !(largest > 0.0 && largest.is_finite()) {
            return None;
        }
        let kept: Vec<usize> = (0..m)
            .filter(|&i| eigen.eigenvalues[i] > RANK_TOLERANCE * largest)
            .collect();
        let k = kept.len();
        let mut transposed = vec![0.0; m * k];
        for (a, row) in transposed.chunks_exact_mut(k).enumerate() {
            for (w, &i) in row.iter_mut().zip(&kept) {
                *w = eigen.eigenvectors[(a, i)] * eigen.eigenvalues[i].sqrt();
            }
        }
        Some(UpdateRows {
            variables,
            k,
            transposed,
        })
    }
}
