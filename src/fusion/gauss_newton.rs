//! Gauss-Newton over the window's free keyframes, as a fixed-lag smoother runs it: the window's
//! structure is known (keyframes in time order, each joined to the few before it), so the normal
//! equations go straight into an [`Envelope`] in time order — no fill-reducing ordering, no
//! symbolic analysis, no sparse pattern — and every buffer lives with the window between
//! keyframes.
//!
//! Each keyframe starts from the previous window's optimum plus a dead-reckoned new state, so
//! one step usually lands at the optimum. The stopping test does not need a second
//! linearisation to say so: after the step the cost is evaluated (residuals only) and the solve
//! stops when the actual decrease matched the quadratic model's prediction to within
//! `function_tolerance × chi2` — the model was then exact over the step, whose end is the
//! model's minimum (the warm-start test of `solver::optimize_warm`). Otherwise it relinearises
//! there and steps again. The other stopping tests are the solver's (function, gradient and
//! parameter tolerances), so the optimum reached is the same.
//!
//! What the envelope cannot express is left to the general solver ([`Outcome::General`]): a
//! free variable outside the window, a group of keyframes with nothing anchoring it (the
//! general solver fixes its gauge), or a system that is not positive definite (it then reports
//! which variable).

use crate::factors::EvaluationError;
use crate::problem::{FactorEntry, Key, Problem, Values, Variable};
use crate::solver::union_find::find_root as find;
use crate::solver::vector::max_abs;
use crate::solver::{SolverError, SolverOptions};

use super::envelope::Envelope;

/// What one window update did.
#[derive(Clone, Debug, PartialEq)]
pub struct WindowUpdate {
    /// Gauss-Newton steps (each one linearisation, one factorisation and one cost evaluation).
    pub iterations: usize,
    pub initial_chi2: f64,
    pub chi2: f64,
    /// Stopped by one of the solver's convergence tests (not the iteration limit, nor a
    /// deferral of what was left to the next keyframe).
    pub converged: bool,
    /// `"window"`: this module's solve; `"general"`: the solver's `optimize` (see the module
    /// documentation for when).
    pub path: &'static str,
}

/// The window solve's result.
pub enum Outcome {
    Solved(WindowUpdate),
    /// The envelope cannot take this window: solve it with the general solver, from the
    /// current values, after `iterations` steps already taken here.
    General {
        iterations: usize,
    },
}

const NONE: usize = usize::MAX;

/// The window's solver state: the layout of the last window and every buffer, reused.
#[derive(Debug, Default)]
pub struct WindowSolver {
    /// Block position of each variable of the problem (`NONE`: not in the window).
    position: Vec<usize>,
    /// Variable index, dimension and first row of each block, in time order.
    blocks: Vec<usize>,
    dims: Vec<usize>,
    offset: Vec<usize>,
    /// The earliest block each block shares a factor with.
    first_block: Vec<usize>,
    /// Union-find over blocks, and whether a component is anchored (prior or fixed variable).
    parent: Vec<usize>,
    anchored: Vec<bool>,
    env: Envelope,
    b: Vec<f64>,
    delta: Vec<f64>,
    /// One factor's error, whitened residual, Jacobian, whitened Jacobian, JᵀJ and Jᵀr.
    error: Vec<f64>,
    residual: Vec<f64>,
    jacobian: Vec<f64>,
    whitened: Vec<f64>,
    gram: Vec<f64>,
    gradient: Vec<f64>,
    /// The window's values before a step (restored when the step's cost is not finite).
    backup: Vec<Box<dyn Variable>>,
}

impl WindowSolver {
    /// Optimises the window whose free keyframes are `keys` (oldest first) by Gauss-Newton,
    /// stopping on `options`' tolerances or once a step leaves at most `deferred_chi2` of chi2
    /// to gain (see [`super::window::WindowOptions::deferred_chi2`]).
    pub fn solve(
        &mut self,
        problem: &mut Problem,
        keys: impl Iterator<Item = Key>,
        options: &SolverOptions,
        deferred_chi2: f64,
    ) -> Result<Outcome, SolverError> {
        let mut values = std::mem::take(&mut problem.values);
        let result =
            self.solve_values(problem.factors(), &mut values, keys, options, deferred_chi2);
        problem.values = values;
        result
    }

    fn solve_values(
        &mut self,
        factors: &[FactorEntry],
        values: &mut Values,
        keys: impl Iterator<Item = Key>,
        options: &SolverOptions,
        deferred_chi2: f64,
    ) -> Result<Outcome, SolverError> {
        if !self.layout(factors, values, keys) {
            return Ok(Outcome::General { iterations: 0 });
        }
        let mut chi2 = self.linearize(factors, values)?;
        if !chi2.is_finite() {
            return Err(SolverError::NonFiniteInitialCost);
        }
        let initial_chi2 = chi2;
        let done = |iterations, chi2, converged| {
            Ok(Outcome::Solved(WindowUpdate {
                iterations,
                initial_chi2,
                chi2,
                converged,
                path: "window",
            }))
        };
        if self.blocks.is_empty() || factors.is_empty() {
            return done(0, chi2, true);
        }
        for iteration in 1..=options.max_iterations {
            if options.gradient_tolerance > 0.0 && max_abs(&self.b) <= options.gradient_tolerance {
                return done(iteration - 1, chi2, true);
            }
            if self.env.factorize().is_err() {
                return Ok(Outcome::General {
                    iterations: iteration - 1,
                });
            }
            self.delta.clone_from(&self.b);
            self.env.solve_in_place(&mut self.delta);
            let predicted: f64 = self.delta.iter().zip(&self.b).map(|(d, b)| d * b).sum();
            self.save(values);
            self.retract(values);
            let trial = self.evaluate(factors, values)?;
            if !trial.is_finite() {
                self.restore(values);
                return Err(SolverError::Diverged { iteration });
            }
            let decrease = chi2 - trial;
            let relative = decrease / chi2.max(f64::MIN_POSITIVE);
            let ftol = options.function_tolerance;
            let converged = (ftol > 0.0
                && (relative.abs() <= ftol || (decrease - predicted).abs() <= ftol * trial))
                || (options.parameter_tolerance > 0.0
                    && max_abs(&self.delta) <= options.parameter_tolerance);
            // Lazy convergence: the step left about |decrease − predicted| of chi2 to gain; at
            // most `deferred_chi2` of it is left to the next keyframe's step.
            let deferred = (decrease - predicted).abs() <= deferred_chi2;
            if converged || deferred || iteration == options.max_iterations {
                return done(iteration, trial, converged);
            }
            chi2 = self.linearize(factors, values)?;
        }
        done(options.max_iterations, chi2, false)
    }

    /// Numbers the window's blocks and lays out the envelope; `false` when the window's
    /// system is not one this solver takes (see the module documentation).
    fn layout(
        &mut self,
        factors: &[FactorEntry],
        values: &Values,
        keys: impl Iterator<Item = Key>,
    ) -> bool {
        self.position.clear();
        self.position.resize(values.len(), NONE);
        self.blocks.clear();
        self.dims.clear();
        self.offset.clear();
        let mut n = 0;
        for key in keys {
            let Some(v) = values.index_of(key) else {
                return false;
            };
            if values.is_fixed(v) || self.position[v] != NONE {
                return false;
            }
            self.position[v] = self.blocks.len();
            self.blocks.push(v);
            let d = values.variable(v).tangent_dim();
            self.dims.push(d);
            self.offset.push(n);
            n += d;
        }
        let count = self.blocks.len();
        self.first_block.clear();
        self.first_block.extend(0..count);
        self.parent.clear();
        self.parent.extend(0..count);
        self.anchored.clear();
        self.anchored.resize(count, false);
        let (mut rows, mut cols) = (0, 0);
        for f in factors {
            let vars = f.variables();
            let mut earliest = NONE;
            let mut width = 0;
            let mut free = 0;
            let mut touches_fixed = false;
            for &v in vars {
                width += values.variable(v).tangent_dim();
                match self.position[v] {
                    NONE if values.is_fixed(v) => touches_fixed = true,
                    NONE => return false,
                    p => {
                        earliest = earliest.min(p);
                        free += 1;
                    }
                }
            }
            rows = rows.max(f.factor.residual_dim());
            cols = cols.max(width);
            if earliest == NONE {
                continue;
            }
            for &v in vars {
                let p = self.position[v];
                if p != NONE {
                    self.first_block[p] = self.first_block[p].min(earliest);
                    let (a, b) = (find(&mut self.parent, p), find(&mut self.parent, earliest));
                    self.parent[a] = b;
                }
            }
            if free == 1 || touches_fixed {
                self.anchored[earliest] = true;
            }
        }
        // Every group of keyframes needs a prior or a fixed neighbour, as the general solver's
        // gauge anchoring would otherwise fix one of them.
        for p in 0..count {
            if self.anchored[p] {
                let root = find(&mut self.parent, p);
                self.anchored[root] = true;
            }
        }
        for p in 0..count {
            let root = find(&mut self.parent, p);
            if !self.anchored[root] {
                return false;
            }
        }
        self.env.reset(&self.dims, &self.first_block);
        self.b.resize(n, 0.0);
        self.delta.resize(n, 0.0);
        self.error.resize(rows, 0.0);
        self.residual.resize(rows, 0.0);
        self.jacobian.resize(rows * cols, 0.0);
        self.whitened.resize(rows * cols, 0.0);
        self.gram.resize(cols * cols, 0.0);
        self.gradient.resize(cols, 0.0);
        true
    }

    /// Linearises every factor at `values` into H (the envelope) and b = −Jᵀr; returns chi2.
    fn linearize(
        &mut self,
        factors: &[FactorEntry],
        values: &Values,
    ) -> Result<f64, EvaluationError> {
        #[cfg(target_arch = "x86_64")]
        if crate::solver::simd::has_wide_vectors() {
            // SAFETY: the CPU has the features `linearize_wide` is compiled for.
            return unsafe { self.linearize_wide(factors, values) };
        }
        self.linearize_with(factors, values)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn linearize_wide(
        &mut self,
        factors: &[FactorEntry],
        values: &Values,
    ) -> Result<f64, EvaluationError> {
        self.linearize_with(factors, values)
    }

    #[inline(always)]
    fn linearize_with(
        &mut self,
        factors: &[FactorEntry],
        values: &Values,
    ) -> Result<f64, EvaluationError> {
        self.env.clear();
        self.b.fill(0.0);
        let mut refs: Vec<&dyn Variable> = Vec::with_capacity(4);
        let mut starts = [0usize; 16];
        let mut total = 0.0;
        for f in factors {
            let vars = f.variables();
            refs.clear();
            refs.extend(vars.iter().map(|&v| values.variable(v)));
            let d = f.factor.residual_dim();
            let mut cols = 0;
            let mut local_starts = Vec::new();
            let starts: &mut [usize] = if vars.len() <= starts.len() {
                &mut starts[..vars.len()]
            } else {
                local_starts.resize(vars.len(), 0);
                &mut local_starts
            };
            for (k, r) in refs.iter().enumerate() {
                starts[k] = cols;
                cols += r.tangent_dim();
            }
            let (e, r) = (&mut self.error[..d], &mut self.residual[..d]);
            let (jac, wj) = (
                &mut self.jacobian[..d * cols],
                &mut self.whitened[..d * cols],
            );
            f.factor.evaluate(&refs, e, Some(jac))?;
            f.sqrt_information.whiten_vector(e, r);
            f.sqrt_information.whiten_jacobian(jac, cols, wj);
            total += match &f.robust {
                Some(kernel) => kernel.correct(r, wj, cols),
                None => r.iter().map(|v| v * v).sum(),
            };
            // The lower triangle of the factor's JᵀJ, and Jᵀr, row by row (whitened rows are
            // often sparse: zero entries are skipped).
            let (gram, gradient) = (&mut self.gram[..cols * cols], &mut self.gradient[..cols]);
            gram.fill(0.0);
            gradient.fill(0.0);
            for (row, &rk) in wj.chunks_exact(cols).zip(r.iter()) {
                for (i, &ji) in row.iter().enumerate() {
                    if ji != 0.0 {
                        gradient[i] += ji * rk;
                        for (g, &jj) in gram[i * cols..i * cols + i + 1].iter_mut().zip(row) {
                            *g += ji * jj;
                        }
                    }
                }
            }
            let gram_at = |x: usize, y: usize| {
                if x >= y {
                    gram[x * cols + y]
                } else {
                    gram[y * cols + x]
                }
            };
            for (li, &vi) in vars.iter().enumerate() {
                let a = self.position[vi];
                if a == NONE {
                    continue;
                }
                let (oa, da, ci) = (self.offset[a], self.dims[a], starts[li]);
                for (bq, g) in self.b[oa..oa + da].iter_mut().zip(&gradient[ci..ci + da]) {
                    *bq -= g;
                }
                for (lj, &vj) in vars.iter().enumerate() {
                    let bp = self.position[vj];
                    if bp == NONE || bp > a || (bp == a && lj != li) {
                        continue;
                    }
                    let (ob, db, cj) = (self.offset[bp], self.dims[bp], starts[lj]);
                    for ii in 0..da {
                        let row = oa + ii;
                        let first = self.env.first(row);
                        let stored = self.env.row_mut(row);
                        let width = if bp == a { ii + 1 } else { db };
                        for jj in 0..width {
                            stored[ob + jj - first] += gram_at(ci + ii, cj + jj);
                        }
                    }
                }
            }
        }
        Ok(total)
    }

    /// chi2 at `values` (residuals only).
    fn evaluate(
        &mut self,
        factors: &[FactorEntry],
        values: &Values,
    ) -> Result<f64, EvaluationError> {
        let mut refs: Vec<&dyn Variable> = Vec::with_capacity(4);
        let mut total = 0.0;
        for f in factors {
            refs.clear();
            refs.extend(f.variables().iter().map(|&v| values.variable(v)));
            let d = f.factor.residual_dim();
            total += f.chi2(&refs, &mut self.error[..d], &mut self.residual[..d])?;
        }
        Ok(if total.is_finite() {
            total
        } else {
            f64::INFINITY
        })
    }

    fn save(&mut self, values: &Values) {
        self.backup.truncate(self.blocks.len());
        for (p, &v) in self.blocks.iter().enumerate() {
            let variable = values.variable(v);
            match self.backup.get_mut(p) {
                Some(saved) => {
                    if !saved.assign_from(variable) {
                        *saved = variable.clone_box();
                    }
                }
                None => self.backup.push(variable.clone_box()),
            }
        }
    }

    fn restore(&self, values: &mut Values) {
        for (saved, &v) in self.backup.iter().zip(&self.blocks) {
            values.set(v, saved.as_ref());
        }
    }

    fn retract(&self, values: &mut Values) {
        for (p, &v) in self.blocks.iter().enumerate() {
            let (o, d) = (self.offset[p], self.dims[p]);
            values.variable_mut(v).retract(&self.delta[o..o + d]);
        }
    }
}
