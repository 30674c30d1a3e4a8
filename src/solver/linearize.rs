//! Evaluation and linearisation: whitened, robustified residuals and Jacobians accumulated
//! straight into `H = JᵀJ` (lower triangle, in the fixed [`BlockPattern`]) and `b = −Jᵀr`.

use std::borrow::Borrow;
use std::ops::ControlFlow;

use crate::factors::EvaluationError;
use crate::problem::FactorEntry;
use crate::problem::{Key, Values, Variable};

use super::budget::{Budget, Unlimited};
use super::structure::{BlockOrdering, BlockPattern, ScalarRows};

mod chunk;
mod fixed;
mod split;

use split::Split;

/// The block number of each variable when free variables are numbered in index order and fixed
/// ones are skipped — the numbering of [`free_adjacency`]'s graph, which every system sharing its
/// ordering (the solve and the chordal initialisation) must use. Also returns the block count.
pub fn free_blocks(fixed: impl IntoIterator<Item = bool>) -> (Vec<Option<usize>>, usize) {
    let mut next = 0;
    let blocks = fixed
        .into_iter()
        .map(|is_fixed| {
            (!is_fixed).then(|| {
                next += 1;
                next - 1
            })
        })
        .collect();
    (blocks, next)
}

/// The graph of free variables (numbered by [`free_blocks`]) that share a factor.
pub fn free_adjacency<E: Borrow<FactorEntry>>(factors: &[E], fixed: &[bool]) -> Vec<Vec<usize>> {
    let (block, count) = free_blocks(fixed.iter().copied());
    // Each list sized exactly first: growing thousands of small vectors by doubling cost more
    // than the ordering itself on small pose graphs.
    let mut degree = vec![0usize; count];
    let mut blocks = Vec::with_capacity(8);
    for f in factors {
        blocks.clear();
        blocks.extend(f.borrow().variables().iter().filter_map(|&v| block[v]));
        for &a in &blocks {
            degree[a] += blocks.len() - 1;
        }
    }
    let mut adjacency: Vec<Vec<usize>> = degree.iter().map(|&d| Vec::with_capacity(d)).collect();
    for f in factors {
        let f = f.borrow();
        blocks.clear();
        blocks.extend(f.variables().iter().filter_map(|&v| block[v]));
        for &a in &blocks {
            for &b in &blocks {
                if a != b {
                    adjacency[a].push(b);
                }
            }
        }
    }
    adjacency
}

/// Maps problem variables to blocks of the linear system; fixed variables get none.
#[derive(Debug)]
pub struct SystemLayout {
    /// Elimination position of each variable (indexed like `Values`), `None` when fixed.
    pub position_of_var: Vec<Option<usize>>,
    /// Variable index at each elimination position.
    pub var_at: Vec<usize>,
    pub pattern: BlockPattern,
    /// Per factor, the H blocks it contributes: (local i, local j, pair) with pos(i) ≥ pos(j).
    slot_start: Vec<usize>,
    slots: Vec<(u8, u8, usize)>,
    /// Factors in the order linearisation visits them: by the first elimination position they
    /// touch, so consecutive factors write neighbouring parts of H (in BA, one point's column at
    /// a time instead of a cache miss per observation).
    visit_order: Vec<usize>,
    max_residual: usize,
    max_cols: usize,
    /// How linearisation shares the factors between threads (`None`: on the calling thread).
    split: Option<Split>,
}

impl SystemLayout {
    /// `fixed[v]` says whether variable `v` is held constant in this solve.
    pub fn new<E: Borrow<FactorEntry>>(factors: &[E], values: &Values, fixed: &[bool]) -> Self {
        let ordering = BlockOrdering::amd(free_adjacency(factors, fixed));
        Self::with_ordering(factors, values, fixed, &ordering, ScalarRows::Listed)
    }

    /// As [`SystemLayout::new`] with an ordering of [`free_adjacency`]'s graph computed earlier;
    /// its pattern lists the scalar rows as `rows` says.
    pub fn with_ordering<E: Borrow<FactorEntry>>(
        factors: &[E],
        values: &Values,
        fixed: &[bool],
        ordering: &BlockOrdering,
        rows: ScalarRows,
    ) -> Self {
        let (block_of_var, _) = free_blocks(fixed.iter().copied());
        let free: Vec<usize> = (0..values.len()).filter(|&v| !fixed[v]).collect();
        let (mut max_residual, mut max_cols) = (0, 0);
        for f in factors {
            let f = f.borrow();
            max_residual = max_residual.max(f.factor.residual_dim());
            max_cols = max_cols.max(
                f.variables()
                    .iter()
                    .map(|&v| values.variable(v).tangent_dim())
                    .sum(),
            );
        }
        let dims: Vec<usize> = free
            .iter()
            .map(|&v| values.variable(v).tangent_dim())
            .collect();
        let pattern = BlockPattern::with_ordering_rows(&dims, ordering, rows);
        let position_of_var: Vec<Option<usize>> = block_of_var
            .iter()
            .map(|b| b.map(|b| pattern.position[b]))
            .collect();
        let var_at: Vec<usize> = pattern.block_at.iter().map(|&b| free[b]).collect();
        let (slot_start, slots) = slots(factors, &position_of_var, &pattern);
        let visit_order = visit_order(factors, &position_of_var, pattern.block_at.len());
        Self {
            position_of_var,
            var_at,
            pattern,
            slot_start,
            slots,
            visit_order,
            max_residual,
            max_cols,
            split: None,
        }
    }

    /// Linearises on up to `threads` threads from now on, where the structure lets the factors
    /// be cut into chunks that write apart (`linearize/split.rs`); returns how many chunks it uses (1: the
    /// calling thread alone). [`Scratch`]es made before this do not use the split.
    pub fn use_threads<E: Borrow<FactorEntry>>(&mut self, factors: &[E], threads: usize) -> usize {
        self.split = split::split(factors, self, threads);
        self.split.as_ref().map_or(1, |s| s.chunks.len())
    }

    pub fn n(&self) -> usize {
        self.pattern.n
    }

    /// Threads linearisation runs on ([`SystemLayout::use_threads`]).
    pub fn threads(&self) -> usize {
        self.split.as_ref().map_or(1, |s| s.chunks.len())
    }

    pub fn key_at_row(&self, values: &Values, row: usize) -> Key {
        values.key(self.var_at[self.pattern.block_of_row(row)])
    }

    /// Applies the step `delta` (in elimination order) to the free variables of `values`.
    pub fn retract(&self, values: &mut Values, delta: &[f64]) {
        for (p, &v) in self.var_at.iter().enumerate() {
            let o = self.pattern.offset[p];
            values
                .variable_mut(v)
                .retract(&delta[o..o + self.pattern.dim[p]]);
        }
    }
}

/// Reusable per-evaluation scratch buffers: the calling thread's, and with a split those of
/// each other thread with its private copy of the shared tail of H and b.
#[derive(Debug, Default)]
pub struct Scratch {
    own: Buffers,
    helpers: Vec<Helper>,
}

/// One thread's per-factor buffers.
#[derive(Debug, Default)]
struct Buffers {
    error: Vec<f64>,
    residual: Vec<f64>,
    jacobian: Vec<f64>,
    whitened: Vec<f64>,
    /// JᵀJ (cols × cols, both triangles) and Jᵀr of one factor.
    gram: Vec<f64>,
    gradient: Vec<f64>,
}

/// A thread other than the caller's: its buffers and its copies of H's and b's shared tails.
#[derive(Debug, Default)]
struct Helper {
    buffers: Buffers,
    h: Vec<f64>,
    b: Vec<f64>,
}

impl Buffers {
    fn new(layout: &SystemLayout) -> Self {
        let (d, c) = (layout.max_residual, layout.max_cols);
        Self {
            error: vec![0.0; d],
            residual: vec![0.0; d],
            jacobian: vec![0.0; d * c],
            whitened: vec![0.0; d * c],
            gram: vec![0.0; c * c],
            gradient: vec![0.0; c],
        }
    }
}

impl Scratch {
    pub fn new(layout: &SystemLayout) -> Self {
        let helpers = match &layout.split {
            Some(split) => (1..split.chunks.len())
                .map(|_| Helper {
                    buffers: Buffers::new(layout),
                    h: vec![0.0; split.shared_values(layout.pattern.nnz())],
                    b: vec![0.0; split.shared_rows(layout.n())],
                })
                .collect(),
            None => Vec::new(),
        };
        Self {
            own: Buffers::new(layout),
            helpers,
        }
    }
}

/// Linearises every factor at `values`; fills `h` (pattern values) and `b = −Jᵀr`, returns chi2.
pub fn linearize<E: Borrow<FactorEntry> + Sync>(
    factors: &[E],
    values: &Values,
    layout: &SystemLayout,
    scratch: &mut Scratch,
    h: &mut [f64],
    b: &mut [f64],
) -> Result<f64, EvaluationError> {
    match linearize_within(factors, values, layout, scratch, h, b, &Unlimited)? {
        ControlFlow::Continue(chi2) => Ok(chi2),
        ControlFlow::Break(()) => unreachable!("an unlimited budget never stops"),
    }
}

/// [`linearize`] that checks `budget` every [`super::budget::FACTORS_PER_CHECK`] factors;
/// `Break` leaves `h` and `b` partly filled.
pub fn linearize_within<E: Borrow<FactorEntry> + Sync>(
    factors: &[E],
    values: &Values,
    layout: &SystemLayout,
    scratch: &mut Scratch,
    h: &mut [f64],
    b: &mut [f64],
    budget: &dyn Budget,
) -> Result<ControlFlow<(), f64>, EvaluationError> {
    chunk::run::<E, true>(factors, values, layout, scratch, h, b, budget)
}

/// [`linearize_within`] for `b = −Jᵀr` and chi2 only, leaving H alone: what a step with an
/// earlier factorisation needs (the factor's `JᵀJ` and its scatter are most of the work).
pub fn gradient_within<E: Borrow<FactorEntry> + Sync>(
    factors: &[E],
    values: &Values,
    layout: &SystemLayout,
    scratch: &mut Scratch,
    b: &mut [f64],
    budget: &dyn Budget,
) -> Result<ControlFlow<(), f64>, EvaluationError> {
    chunk::run::<E, false>(factors, values, layout, scratch, &mut [], b, budget)
}

/// One factor's whitened, robustified normal equations at `refs` (its variables in key order,
/// `cols` tangent columns in all): `JᵀJ` (both triangles, only without `HESSIAN` skipped) into
/// `scratch.gram[..cols²]` and `Jᵀr` into `scratch.gradient[..cols]`; returns its chi2. The batch
/// linearisation and the incremental engine both take a factor's blocks from here.
#[inline(always)]
fn factor_gram<const HESSIAN: bool>(
    entry: &FactorEntry,
    refs: &[&dyn Variable],
    d: usize,
    cols: usize,
    buffers: &mut Buffers,
) -> Result<f64, EvaluationError> {
    let Buffers {
        error,
        residual,
        jacobian,
        whitened,
        gram,
        gradient,
    } = buffers;
    let (e, r, jac, wj) = (
        &mut error[..d],
        &mut residual[..d],
        &mut jacobian[..d * cols],
        &mut whitened[..d * cols],
    );
    entry.factor.evaluate(refs, e, Some(jac))?;
    let (gram, gradient) = (&mut gram[..cols * cols], &mut gradient[..cols]);
    let fixed_size = match entry.robust {
        None => fixed::whitened_gram_fixed::<HESSIAN>(
            &entry.sqrt_information,
            d,
            cols,
            e,
            jac,
            gram,
            gradient,
        ),
        Some(_) => None,
    };
    if let Some(chi2) = fixed_size {
        return Ok(chi2);
    }
    entry.sqrt_information.whiten_vector(e, r);
    entry.sqrt_information.whiten_jacobian(jac, cols, wj);
    let chi2 = match &entry.robust {
        Some(kernel) => kernel.correct(r, wj, cols),
        None => r.iter().map(|v| v * v).sum(),
    };
    // The factor's own JᵀJ and Jᵀr as rank-1 updates row by row (contiguous, vectorisable).
    gram.fill(0.0);
    gradient.fill(0.0);
    for (row, &rk) in wj.chunks_exact(cols).zip(r.iter()) {
        for (i, &ji) in row.iter().enumerate() {
            gradient[i] += ji * rk;
            if HESSIAN {
                for (g, &jj) in gram[i * cols..(i + 1) * cols].iter_mut().zip(row) {
                    *g += ji * jj;
                }
            }
        }
    }
    Ok(chi2)
}

/// [`factor_gram`] with the Hessian, into buffers grown to fit: for callers linearising one
/// factor at a time (the incremental engine). Returns chi2, `JᵀJ` (cols × cols) and `Jᵀr`.
pub fn factor_normal_equations<'s>(
    entry: &FactorEntry,
    refs: &[&dyn Variable],
    scratch: &'s mut Scratch,
) -> Result<(f64, &'s [f64], &'s [f64]), EvaluationError> {
    let d = entry.factor.residual_dim();
    let cols: usize = refs.iter().map(|r| r.tangent_dim()).sum();
    let scratch = &mut scratch.own;
    for (buffer, len) in [
        (&mut scratch.error, d),
        (&mut scratch.residual, d),
        (&mut scratch.jacobian, d * cols),
        (&mut scratch.whitened, d * cols),
        (&mut scratch.gram, cols * cols),
        (&mut scratch.gradient, cols),
    ] {
        if buffer.len() < len {
            buffer.resize(len, 0.0);
        }
    }
    let chi2 = factor_gram::<true>(entry, refs, d, cols, scratch)?;
    Ok((
        chi2,
        &scratch.gram[..cols * cols],
        &scratch.gradient[..cols],
    ))
}

/// `y = H x` for the symmetric matrix stored as its lower triangle.
pub fn symmetric_multiply(pattern: &BlockPattern, h: &[f64], x: &[f64], y: &mut [f64]) {
    assert!(
        pattern.has_scalar_rows(),
        "the pattern's scalar rows were forgotten"
    );
    y.fill(0.0);
    for c in 0..pattern.n {
        let column = pattern.col_ptr[c]..pattern.col_ptr[c + 1];
        for (&r, &h_rc) in pattern.row_idx[column.clone()].iter().zip(&h[column]) {
            y[r] += h_rc * x[c];
            if r != c {
                y[c] += h_rc * x[r];
            }
        }
    }
}

/// Per factor (from `slot_start[f]`), the pairs of its free variables' blocks in the lower
/// triangle: (local index, local index, the pattern's pair).
fn slots<E: Borrow<FactorEntry>>(
    factors: &[E],
    position_of_var: &[Option<usize>],
    pattern: &BlockPattern,
) -> (Vec<usize>, Vec<(u8, u8, usize)>) {
    let mut slot_start = Vec::with_capacity(factors.len() + 1);
    let mut slots = Vec::with_capacity(
        factors
            .iter()
            .map(|f| {
                let k = f.borrow().variables().len();
                k * (k + 1) / 2
            })
            .sum(),
    );
    slot_start.push(0);
    for f in factors {
        let vars = f.borrow().variables();
        for (li, &vi) in vars.iter().enumerate() {
            for (lj, &vj) in vars.iter().enumerate() {
                if let (Some(a), Some(b)) = (position_of_var[vi], position_of_var[vj]) {
                    if a >= b {
                        let pair = pattern
                            .pair(a, b)
                            .expect("pattern holds every factor's pairs");
                        slots.push((li as u8, lj as u8, pair));
                    }
                }
            }
        }
        slot_start.push(slots.len());
    }
    (slot_start, slots)
}

/// The factors sorted by the first elimination position among their variables, by a counting
/// sort (stable, linear): a comparison sort calling the key closure per comparison cost ~5% of
/// a small pose graph's solve. `nb` blocks; a factor whose variables are all fixed sorts last.
fn visit_order<E: Borrow<FactorEntry>>(
    factors: &[E],
    position_of_var: &[Option<usize>],
    nb: usize,
) -> Vec<usize> {
    let first: Vec<usize> = factors
        .iter()
        .map(|f| {
            f.borrow()
                .variables()
                .iter()
                .filter_map(|&v| position_of_var[v])
                .min()
                .unwrap_or(nb)
        })
        .collect();
    // Positions 0..=nb: a factor whose variables are all fixed sorts last, at nb.
    let mut start = vec![0usize; nb + 3];
    for &p in &first {
        start[p + 2] += 1;
    }
    for p in 2..start.len() {
        start[p] += start[p - 1];
    }
    let mut visit_order = vec![0usize; factors.len()];
    for (f, &p) in first.iter().enumerate() {
        visit_order[start[p + 1]] = f;
        start[p + 1] += 1;
    }
    visit_order
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::BetweenSe2;
    use crate::geometry::Se2;
    use crate::problem::Problem;

    /// A factor between two fixed variables has no block in the system; the layout still
    /// visits it (last) and linearisation skips its blocks.
    #[test]
    fn a_factor_between_fixed_variables_is_laid_out() {
        let mut problem = Problem::new();
        for k in 0..3u64 {
            problem
                .add_variable(k, Box::new(Se2::new(k as f64, 0.0, 0.0)))
                .unwrap();
        }
        let information = nalgebra::DMatrix::identity(3, 3);
        for (a, b) in [(0u64, 1u64), (1, 2)] {
            let z = Se2::new(1.0, 0.0, 0.0);
            let factor = Box::new(BetweenSe2::new(a, b, z));
            problem.add_factor(factor, &information, None, "e").unwrap();
        }
        let fixed = [true, true, false];
        let layout = SystemLayout::new(problem.factors(), &problem.values, &fixed);
        assert_eq!(layout.visit_order.len(), 2);
        assert_eq!(layout.visit_order[1], 0, "the all-fixed factor comes last");
        let mut scratch = Scratch::new(&layout);
        let mut h = vec![0.0; layout.pattern.nnz()];
        let mut b = vec![0.0; layout.n()];
        linearize(
            problem.factors(),
            &problem.values,
            &layout,
            &mut scratch,
            &mut h,
            &mut b,
        )
        .unwrap();
    }
}
