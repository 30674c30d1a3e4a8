//! Solves with the kept factor: forward substitution of the refactored columns (from the
//! per-row sums the kept columns leave) and back substitution from the roots down, into the
//! subtrees whose separator moved.

use super::{dense, BlockFactor};

/// What back substitution writes, per scalar: the solution `x` of `Lᵀ x = y`, and the value
/// each column's subtree was last solved against (`propagated`).
pub struct Solution<'a> {
    pub x: &'a mut [f64],
    pub propagated: &'a mut [f64],
}

impl BlockFactor {
    /// Before the columns of `order` are refactored: takes what they contributed to `partial`
    /// out of it (see [`BlockFactor::forward`]), with their values and `y` as they still are.
    pub fn withdraw(&self, order: &[usize], offset: &[usize], y: &[f64], partial: &mut [f64]) {
        for &k in order {
            let (dk, ok) = (self.dim[k], offset[k]);
            let column = &self.columns[k];
            for &(u, at) in &column.rows {
                let (du, ou) = (self.dim[u as usize], offset[u as usize]);
                let l_uk = &column.blocks[at as usize..at as usize + du * dk];
                dense::sub_mul_vector(&mut partial[ou..ou + du], l_uk, &y[ok..ok + dk], du, dk);
            }
        }
    }

    /// Forward substitution `L y = b` for the columns of `order` (in that order), whose
    /// right-hand side `rhs(r, out)` writes; every other column keeps its `y` (it depends only
    /// on its subtree). `y` and `offset` index scalars per variable.
    ///
    /// `partial` holds, per row u, `Σ_k L_uk y_k` over the columns k stored now: the kept
    /// columns' part stays valid across updates (neither their blocks nor their `y` change), so
    /// a refactored row takes it from there instead of walking every column that reaches it
    /// (near the root, most of the map). [`BlockFactor::withdraw`] takes the refactored
    /// columns' old part out first; this adds their new part as each is solved.
    pub fn forward(
        &self,
        order: &[usize],
        offset: &[usize],
        y: &mut [f64],
        partial: &mut [f64],
        mut rhs: impl FnMut(usize, &mut [f64]),
    ) {
        let mut z = Vec::new();
        let mut negated = Vec::new();
        for &r in order {
            let (d, o) = (self.dim[r], offset[r]);
            z.clear();
            z.resize(d, 0.0);
            rhs(r, &mut z);
            for (zi, p) in z.iter_mut().zip(&partial[o..o + d]) {
                *zi -= p;
            }
            let column = &self.columns[r];
            dense::forward(&column.diagonal, &mut z, d);
            y[o..o + d].copy_from_slice(&z);
            negated.clear();
            negated.extend(z.iter().map(|v| -v));
            for &(u, at) in &column.rows {
                let (du, ou) = (self.dim[u as usize], offset[u as usize]);
                let l_ur = &column.blocks[at as usize..at as usize + du * d];
                dense::sub_mul_vector(&mut partial[ou..ou + du], l_ur, &negated, du, d);
            }
        }
    }

    /// Back substitution `Lᵀ x = y` from the roots down, into `solution.x` (which holds the
    /// previous solution). A column is solved again when it was refactored (`in_order`) or
    /// when one of its rows moved by more than `threshold` (max-norm); its subtree is entered
    /// only then. `threshold = 0` solves every column below a change. Returns the columns
    /// solved and appends those written to `x` (refactored, or moved) to `changed_out`.
    ///
    /// A column *moved* when its solution is more than `threshold` from `propagated`, the
    /// value its children were last solved against (updated then). Measured against the
    /// previous solution instead, a parent drifting by less than the threshold at every update
    /// never reached its subtree, and the streamed estimate drifted from the solution (10k
    /// stream: 4.5e-4 relative chi2 above the optimum). A column neither refactored nor moved
    /// keeps its value, so what is published is what its subtree was solved with.
    pub fn back_substitute(
        &mut self,
        in_order: &[bool],
        offset: &[usize],
        y: &[f64],
        solution: Solution<'_>,
        threshold: f64,
        changed_out: &mut Vec<usize>,
    ) -> usize {
        let Solution { x, propagated } = solution;
        let mut stack: Vec<u32> = self.roots.iter().copied().collect();
        let mut solved = 0;
        let mut z = Vec::new();
        let first_changed = changed_out.len();
        while let Some(v) = stack.pop() {
            let v = v as usize;
            // Nearly every column popped is solved and moves (10k stream: 13.67 M popped, 13.65 M
            // solved), so the next one is most often its last child, pushed below.
            if let Some(&next) = self.children[v].last().or(stack.last()) {
                prefetch_column(&self.columns[next as usize]);
            }
            let column = &self.columns[v];
            let refactored = in_order[v];
            if !refactored && !column.rows.iter().any(|&(u, _)| self.changed[u as usize]) {
                continue;
            }
            let d = self.dim[v];
            let o = offset[v];
            z.clear();
            z.extend_from_slice(&y[o..o + d]);
            for &(u, at) in &column.rows {
                let du = self.dim[u as usize];
                let ou = offset[u as usize];
                let l_uv = &column.blocks[at as usize..at as usize + du * d];
                dense::sub_mul_transpose_vector(&mut z, l_uv, &x[ou..ou + du], du, d);
            }
            dense::backward(&column.diagonal, &mut z, d);
            solved += 1;
            let moved = z
                .iter()
                .zip(&propagated[o..o + d])
                .any(|(a, b)| (a - b).abs() > threshold);
            if moved {
                propagated[o..o + d].copy_from_slice(&z);
                self.changed[v] = true;
            }
            if moved || refactored {
                x[o..o + d].copy_from_slice(&z);
                changed_out.push(v);
                stack.extend_from_slice(&self.children[v]);
            }
        }
        for &v in &changed_out[first_changed..] {
            self.changed[v] = false;
        }
        solved
    }
}

/// Asks for the next column's rows, diagonal and first 2 KB of blocks (7 blocks of 6×6, 28
/// of 3×3) while this one is solved: the walk waits on memory, column after column (`perf
/// annotate` of the 10k stream: on the first product of each block, the diagonal's load and
/// the scan of the rows). With the next column guessed as the last child, against the stack's
/// top and two lines of blocks (measured together), the solve phase relative to ordering,
/// in-process: 10k 1.74 / 1.79 / 1.89 / 1.92 → 1.54 / 1.40 / 1.57 / 1.55, sphere2500 1.26 /
/// 1.34 / 1.24 / 1.29 → 1.17 / 1.15 / 1.06 / 1.17; 4 KB of blocks was no faster than 2 KB
/// (see BENCHMARKS.md).
#[inline(always)]
fn prefetch_column(column: &super::Column) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let blocks = column.blocks.as_ptr();
        // SAFETY: a prefetch is a hint that never faults, whatever the address; the pointers
        // are formed with wrapping arithmetic and never dereferenced.
        unsafe {
            _mm_prefetch(column.rows.as_ptr().cast(), _MM_HINT_T0);
            _mm_prefetch(column.diagonal.as_ptr().cast(), _MM_HINT_T0);
            for line in (0..column.blocks.len().min(256)).step_by(8) {
                _mm_prefetch(blocks.wrapping_add(line).cast(), _MM_HINT_T0);
            }
        }
    }
}
