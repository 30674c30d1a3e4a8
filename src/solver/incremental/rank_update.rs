//! New factors added to the kept factor by a rank update along their elimination-tree paths,
//! instead of eliminating those paths again (iSAM1's Givens update, Kaess et al. 2008, here in
//! block Householder form).
//!
//! A factor with Gram matrix `G = WᵀW` (`W`: `k` rows, nonzero only at the factor's variables)
//! changes the normal equations to `H + WᵀW`, and the factor to `L'` with
//!
//! ```text
//!     L' L'ᵀ = L Lᵀ + WᵀW = [L  Wᵀ] [L  Wᵀ]ᵀ
//! ```
//!
//! so `L'` is `[L  Wᵀ]` times an orthogonal matrix that zeroes the `Wᵀ` part. Column by column
//! in rank order, starting at the lowest-ranked variable of `W`: column `c` (`d` scalars) and
//! the `k` columns of `Wᵀ` are rotated by `d` Householder reflections so that `Wᵀ`'s rows at `c`
//! vanish; what is left of `Wᵀ` then lives on `c`'s rows only (`c`'s rows gain the variables it
//! held there, the fill), so the next column is `c`'s parent. The columns changed are one path
//! to the root, the same columns a refactor would eliminate again, at `4·k·d` flops per scalar
//! of each column instead of the column's width: near the root of a large map, where a column
//! reaches hundreds of variables, that is tens of times less.
//!
//! A new variable gets a fresh rank above every other, so its column is a new root that the
//! update fills. Several factors are several groups of rows, merged where their paths meet.
//! The update keeps the order: fill accumulates, and the engine eliminates (and reorders)
//! again when the updates have cost as much as that would (see `IncrementalEngine`).

use std::cmp::Reverse;
use std::collections::BinaryHeap;

use super::{BlockFactor, NotPositiveDefinite, NONE};

/// Rows `W` to add to the factor: `Wᵀ` for each variable of `variables` (`dim` rows of `k`
/// values, row-major), stacked in that order.
#[derive(Debug, Clone, Default)]
pub struct UpdateRows {
    pub variables: Vec<u32>,
    pub k: usize,
    pub transposed: Vec<f64>,
}

/// What [`BlockFactor::add_rows`] changed: the columns of its path, in rank order, and its
/// flops (the Householder reflections).
#[derive(Debug, Default)]
pub struct RankUpdate {
    pub path: Vec<usize>,
    pub flops: f64,
}

impl BlockFactor {
    /// Gives `new` (variables without a column yet) fresh ranks above every other, in that
    /// order, as roots: their columns are built by the next [`BlockFactor::add_rows`].
    pub fn append(&mut self, new: &[usize]) {
        for &v in new {
            self.rank[v] = self.next_rank;
            self.next_rank += 1;
            self.roots.insert(v as u32);
        }
    }

    /// Adds `groups` (each one factor's `W`) to the factor: `L L ᵀ + Σ WᵀW`, by Householder
    /// reflections along the paths from their variables to the root. Before a column changes,
    /// its part of `partial` is withdrawn (with the current `y`); the caller solves the
    /// returned path forward again, which adds the new part. Every variable of the groups has a
    /// column or was [`BlockFactor::append`]ed. On `Err` (a new column without a positive
    /// pivot) the factor is unusable (rebuild it).
    pub fn add_rows(
        &mut self,
        groups: Vec<UpdateRows>,
        offset: &[usize],
        y: &[f64],
        partial: &mut [f64],
    ) -> Result<RankUpdate, NotPositiveDefinite> {
        let mut groups: Vec<UpdateRows> = groups.into_iter().filter(|g| g.k > 0).collect();
        // Each group is due at its lowest-ranked variable: every group meeting there has it
        // as its lowest too (any lower one was due, and merged, before), so the merged rows
        // are due at the lowest of the column's rows, its parent.
        let mut due: BinaryHeap<Reverse<(u64, u32)>> = groups
            .iter()
            .filter_map(|g| self.lowest(&g.variables))
            .collect();
        let mut update = RankUpdate::default();
        let mut result = Ok(());
        while let Some(Reverse((_, c))) = due.pop() {
            let c = c as usize;
            if self.covered[c] {
                continue;
            }
            self.covered[c] = true;
            let meeting: Vec<UpdateRows> = groups
                .extract_if(.., |g| g.variables.contains(&(c as u32)))
                .collect();
            self.withdraw(&[c], offset, y, partial);
            let (merged, flops) = self.rotate_column(c, meeting);
            update.path.push(c);
            update.flops += flops;
            match merged {
                Ok(merged) => {
                    due.extend(self.lowest(&merged.variables));
                    if !merged.variables.is_empty() {
                        groups.push(merged);
                    }
                }
                Err(e) => {
                    result = Err(e);
                    break;
                }
            }
        }
        for &c in &update.path {
            self.covered[c] = false;
        }
        result.map(|()| update)
    }

    /// The lowest-ranked of `variables`, keyed for the min-heap of `add_rows`.
    fn lowest(&self, variables: &[u32]) -> Option<Reverse<(u64, u32)>> {
        variables
            .iter()
            .map(|&v| Reverse((self.rank[v as usize], v)))
            .max()
    }

    /// Rotates column `c` with the rows of `meeting` (every group with a variable at `c`): adds
    /// the groups' other variables to `c`'s rows (fill), zeroes their rows at `c` and returns
    /// them merged, on `c`'s rows, with the flops spent.
    // Kept whole (84 lines): one column's Givens rotations over its merged rows, the inner
    // loop of every rank update.
    fn rotate_column(
        &mut self,
        c: usize,
        meeting: Vec<UpdateRows>,
    ) -> (Result<UpdateRows, NotPositiveDefinite>, f64) {
        let d = self.dim[c];
        self.nnz -= self.column_nnz(c, &self.columns[c]);
        let column = &mut self.columns[c];
        if column.diagonal.is_empty() {
            column.diagonal.resize(d * d, 0.0);
        }
        for &(u, o) in &column.rows {
            self.slot[u as usize] = o;
        }
        for g in &meeting {
            for &u in &g.variables {
                if u as usize != c && self.slot[u as usize] == NONE {
                    let o = column.blocks.len() as u32;
                    column
                        .blocks
                        .resize(column.blocks.len() + self.dim[u as usize] * d, 0.0);
                    column.rows.push((u, o));
                    self.row_columns[u as usize].push((c as u32, o));
                    self.slot[u as usize] = o;
                }
            }
        }
        // `Wᵀ` on c's scalars (`top`, d rows) and on its rows' scalars (`rest`, in `blocks`
        // order): what is left of `rest` is the merged group's `Wᵀ`, with no copy.
        let k: usize = meeting.iter().map(|g| g.k).sum();
        let scalars = column.blocks.len() / d;
        let (mut top, mut rest) = (vec![0.0; d * k], vec![0.0; scalars * k]);
        let mut first = 0;
        for g in &meeting {
            let mut from = 0;
            for &u in &g.variables {
                let du = self.dim[u as usize];
                let (to, row) = match u as usize == c {
                    true => (&mut top, 0),
                    false => (&mut rest, self.slot[u as usize] as usize / d),
                };
                for a in 0..du {
                    let src = &g.transposed[(from + a) * g.k..(from + a + 1) * g.k];
                    to[(row + a) * k + first..(row + a) * k + first + g.k].copy_from_slice(src);
                }
                from += du;
            }
            first += g.k;
        }
        for &(u, _) in &column.rows {
            self.slot[u as usize] = NONE;
        }
        let pivots = householder(
            &mut column.diagonal,
            &mut column.blocks,
            &mut top,
            &mut rest,
            d,
            k,
        );
        let flops = rank_update_flops(k, d, scalars);
        // What is left of `Wᵀ` is on c's rows, in the order of their blocks (the order in which
        // they were stored, unless a dense front stored them otherwise).
        let in_block_order = column.rows.windows(2).all(|w| w[0].1 < w[1].1);
        let variables = match in_block_order {
            true => column.rows.iter().map(|&(u, _)| u).collect(),
            false => {
                let mut rows = column.rows.clone();
                rows.sort_unstable_by_key(|&(_, o)| o);
                rows.into_iter().map(|(u, _)| u).collect()
            }
        };
        let merged = UpdateRows {
            variables,
            k,
            transposed: rest,
        };
        self.nnz += self.column_nnz(c, &self.columns[c]);
        self.kept.forget(c);
        // Fill may have added a row ranked below the parent, or given a new column its first.
        self.reparent(&[c]);
        let merged = pivots.map(|()| merged).map_err(|()| NotPositiveDefinite(c));
        (merged, flops)
    }
}

/// Flops of rotating a column `d` wide with `s` scalar rows against `k` rows of `W`: `d`
/// reflections of `d + s` rows, each `4·k` flops.
pub fn rank_update_flops(k: usize, d: usize, s: usize) -> f64 {
    (4 * k * d * (d + s)) as f64
}

/// Zeroes `top` (`Wᵀ` on column `L_c`'s scalars, `d × k` row-major) against `L_c`: `diagonal`
/// (`d × d` lower triangular, row-major) over `blocks` (`s × d`, row-major, beside `rest`: `Wᵀ`
/// on the column's rows, `s × k`), by `d` Householder reflections of the `d + k` columns
/// `[L_c  Wᵀ]`, each keeping its pivot positive.
/// `Err` when a pivot ends at zero (a column without information).
fn householder(
    diagonal: &mut [f64],
    blocks: &mut [f64],
    top: &mut [f64],
    rest: &mut [f64],
    d: usize,
    k: usize,
) -> Result<(), ()> {
    // Each reflection `j` is `I − β_j u uᵀ` with `u = (1 at column j, v_j on Wᵀ's columns)`.
    let mut v = vec![0.0; d * k];
    let mut beta = vec![0.0; d];
    for j in 0..d {
        let x0 = diagonal[j * d + j];
        let row = &top[j * k..(j + 1) * k];
        let sigma: f64 = row.iter().map(|x| x * x).sum();
        if sigma == 0.0 {
            if x0 > 0.0 {
                continue;
            }
            return Err(());
        }
        let mu = (x0 * x0 + sigma).sqrt();
        // The reflection maps (x0, row) to (μ, 0); v0 without cancellation (Golub & Van Loan,
        // Algorithm 5.1.1), v scaled so that v0 = 1.
        let v0 = if x0 <= 0.0 {
            x0 - mu
        } else {
            -sigma / (x0 + mu)
        };
        beta[j] = 2.0 * v0 * v0 / (sigma + v0 * v0);
        for (vi, &x) in v[j * k..(j + 1) * k].iter_mut().zip(row) {
            *vi = x / v0;
        }
        diagonal[j * d + j] = mu;
        top[j * k..(j + 1) * k].fill(0.0);
        for i in j + 1..d {
            let (a, w) = (&mut diagonal[i * d + j], &mut top[i * k..(i + 1) * k]);
            reflect(a, w, &v[j * k..(j + 1) * k], beta[j]);
        }
        if !(mu > f64::MIN_POSITIVE && mu.is_finite()) {
            return Err(());
        }
    }
    reflect_rows(blocks, rest, &v, &beta, d, k);
    Ok(())
}

/// Applies the reflections to every row of the column's blocks, in order, row by row (one pass
/// over the column): where a rank update spends its time, so compiled with AVX2 + FMA where
/// the CPU has them (see `solver::simd`).
fn reflect_rows(blocks: &mut [f64], wt: &mut [f64], v: &[f64], beta: &[f64], d: usize, k: usize) {
    if crate::solver::simd::has_wide_vectors() {
        // SAFETY: the CPU has the features `reflect_rows_wide` is compiled for.
        unsafe { reflect_rows_wide(blocks, wt, v, beta, d, k) }
    } else {
        reflect_rows_with(blocks, wt, v, beta, d, k)
    }
}

#[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma"))]
fn reflect_rows_wide(
    blocks: &mut [f64],
    wt: &mut [f64],
    v: &[f64],
    beta: &[f64],
    d: usize,
    k: usize,
) {
    reflect_rows_with(blocks, wt, v, beta, d, k)
}

#[inline(always)]
fn reflect_rows_with(
    blocks: &mut [f64],
    wt: &mut [f64],
    v: &[f64],
    beta: &[f64],
    d: usize,
    k: usize,
) {
    for (l, w) in blocks.chunks_exact_mut(d).zip(wt.chunks_exact_mut(k)) {
        for (j, a) in l.iter_mut().enumerate() {
            if beta[j] != 0.0 {
                reflect(a, w, &v[j * k..(j + 1) * k], beta[j]);
            }
        }
    }
}

/// `(a, w) −= β (a + w·v) (1, v)`: one reflection of one row.
#[inline(always)]
fn reflect(a: &mut f64, w: &mut [f64], v: &[f64], beta: f64) {
    let s = beta * (*a + w.iter().zip(v).map(|(w, v)| w * v).sum::<f64>());
    *a -= s;
    for (w, v) in w.iter_mut().zip(v) {
        *w -= s * v;
    }
}
