//! Dense fronts of a refactored part: runs of columns that form one clique are factored as one
//! dense matrix by faer's blocked kernels instead of block by block.
//!
//! A loop closure in a large map refactors long paths of the elimination tree near its root,
//! where each column's rows are the next columns of the path and the same separator `S` beyond
//! it (a supernode). Left-looking, block by block, every column of such a run would walk every
//! earlier column of the run again, each with all of its rows: hundreds of 3×3 products per
//! block, with an index lookup each. As a front, the run `J` and its rows are gathered once into
//! the dense panel `[A_JJ; A_SJ]`, and
//!
//! ```text
//!     L_JJ = chol(A_JJ),    L_SJ = A_SJ L_JJ⁻ᵀ,    U = L_SJ L_SJᵀ
//! ```
//!
//! (Cholesky, triangular solve, symmetric product: blocked dense kernels). `U` is the front's
//! update matrix, what `J` contributes to the columns of `S`: each of them subtracts its part of
//! `U` when it is gathered, instead of walking `J`'s columns (they are marked `covered` for the
//! rest of the refactor, as kept subtrees with an update matrix are).
//!
//! When is a run a clique? After column `r` is gathered, the columns right after it in the order
//! that are rows of `r` form a path of the tree (`r`'s parent is its lowest-ranked row, and a
//! column's rows less its parent are rows of its parent), every column of which has every later
//! one as a row. A front's column stores a block for every later column of the front and for
//! the rows of `S` that it or an earlier column of the front reaches (its symbolic structure).
//!
//! The last front of a refactored part may also be its dense tail: a column whose rows are
//! nearly every column after it starts a front over the rest of the part, whose missing blocks
//! are stored as explicit zeros (the root clique of iSAM2's Bayes tree: the top separators of a
//! large map, and the ring of recent poses a 3D sphere's updates reach).

use std::cmp::Reverse;
use std::collections::BinaryHeap;

use dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::{self as dense_llt, LltError, LltRegularization};
use faer::linalg::matmul::triangular::{self as triangular_matmul, BlockStructure};
use faer::linalg::triangular_solve::solve_lower_triangular_in_place;
use faer::{Accum, MatMut, Par, Spec};

use super::{Accumulator, BlockFactor, KeptApplications, NotPositiveDefinite, NONE};
use crate::solver::incremental::subtree_updates::BASE_BUDGET;

/// A shorter run is eliminated column by column (the dense matrix would not pay for itself).
const MIN_COLUMNS: usize = 12;
/// A tail may start at a column that misses up to this fraction of the columns after it: those
/// blocks are stored as explicit zeros. (The newest variables, eliminated last, often reach
/// only a few of the others: a column of the clique below them misses them.)
const MAX_MISSING: f64 = 0.125;

/// How many columns a front starting at `order[i]` (gathered in `acc`) takes, if one starts
/// there: the rest of the part when `order[i]` reaches nearly all of it (the tail), else the
/// run of columns right after it that are its rows.
pub(super) fn front_at(order: &[usize], i: usize, acc: &Accumulator) -> Option<usize> {
    let later = order.len() - i - 1;
    let rows = acc.entries.len();
    if later + 1 >= MIN_COLUMNS && (later - rows) as f64 <= MAX_MISSING * later as f64 {
        return Some(later + 1);
    }
    let run = order[i + 1..]
        .iter()
        .take_while(|&&u| acc.slot[u] != NONE)
        .count();
    (run + 1 >= MIN_COLUMNS).then_some(run + 1)
}

/// Spare buffers kept at most: about the fronts of one large refactor.
const MAX_SPARE_BUFFERS: usize = 16;

/// The update matrices of the fronts eliminated so far in one refactor, each until the last
/// of its rows is gathered; and the buffers fronts are built in, kept from one refactor to the
/// next.
///
/// A front near the root of a 3D map is a dense matrix of megabytes (sphere2500: a thousand
/// scalars square). Allocated fresh for every update, each of its pages was zeroed again by a
/// page fault: 13% of a sphere2500 stream's time, most of it in the kernel. Reused, a panel
/// is zeroed by one `memset` over memory the process already has, and an update matrix is not
/// zeroed at all (see [`FrontUpdates::update_buffer`]).
#[derive(Debug, Default)]
pub(super) struct FrontUpdates {
    /// `(rank of a row, front, position of the row in the front's rows)`, the lowest rank first.
    due: BinaryHeap<Reverse<(u64, u32, u32)>>,
    fronts: Vec<FrontUpdate>,
    /// Update matrices no longer needed, for the next fronts.
    spare: Vec<Vec<f64>>,
    /// The panel `[A_JJ; A_SJ]` of the front being eliminated, and its gathered columns.
    panel: Vec<f64>,
    gathered: Gathered,
}

/// `U` of one front: its rows `S` in rank order, where each starts in `U` (scalars, one more
/// at the end: `U`'s size), and `U`'s lower triangle, column-major.
#[derive(Debug)]
struct FrontUpdate {
    rows: Vec<u32>,
    offsets: Vec<usize>,
    values: Vec<f64>,
    remaining: usize,
}

impl FrontUpdates {
    fn push(&mut self, rows: Vec<u32>, offsets: Vec<usize>, values: Vec<f64>, rank: &[u64]) {
        let id = self.fronts.len() as u32;
        for (q, &u) in rows.iter().enumerate() {
            self.due.push(Reverse((rank[u as usize], id, q as u32)));
        }
        self.fronts.push(FrontUpdate {
            remaining: rows.len(),
            rows,
            offsets,
            values,
        });
    }

    /// Subtracts from column `r` (rank `rank_r`, being gathered in `acc`) its part of every
    /// front update that reaches it.
    pub(super) fn subtract_due(&mut self, rank_r: u64, dims: &[usize], acc: &mut Accumulator) {
        while let Some(&Reverse((rank, f, q))) = self.due.peek() {
            if rank != rank_r {
                break;
            }
            self.due.pop();
            let front = &mut self.fronts[f as usize];
            let (q, n) = (q as usize, front.offsets[front.rows.len()]);
            let (oq, d) = (front.offsets[q], dims[front.rows[q] as usize]);
            // Column j of the row's columns of U, from row `from` on (contiguous).
            let values = &front.values;
            let u_column = |j: usize, from: usize| &values[(oq + j) * n + from..(oq + j + 1) * n];
            let diagonal = acc.diagonal_mut();
            for j in 0..d {
                for (i, v) in u_column(j, oq + j).iter().take(d - j).enumerate() {
                    diagonal[(i + j) * d + j] -= v;
                }
            }
            // Later rows of S come later in it (rank order): below the diagonal of U.
            for p in q + 1..front.rows.len() {
                let (u, op) = (front.rows[p] as usize, front.offsets[p]);
                let du = dims[u];
                let block = acc.block_mut(u, du);
                for j in 0..d {
                    for (i, v) in u_column(j, op).iter().take(du).enumerate() {
                        block[i * d + j] -= v;
                    }
                }
            }
            front.remaining -= 1;
            if front.remaining == 0 {
                let values = std::mem::take(&mut front.values);
                self.recycle(values);
            }
        }
    }

    /// The refactor is over: nothing is due any more. The buffers kept for the next refactor
    /// are cut to the factor's size (`factor_bytes`), and at least [`BASE_BUDGET`] (the floor
    /// of the kept subtree updates), the largest kept first. A large loop closure's fronts in a
    /// 2D map are update matrices of tens of megabytes: kept whole, they raised a 10k stream's
    /// peak memory from 199 to 230 MB. Without the floor a sphere2500 stream dropped buffers
    /// it needed again and spent 1.4–1.9 s in the kernel, with it 0.8–0.9 s (the 10k stream's
    /// peak: 205 MB without, 209 MB with).
    pub(super) fn end_refactor(&mut self, factor_bytes: usize) {
        let budget = BASE_BUDGET.max(factor_bytes);
        self.due.clear();
        for front in std::mem::take(&mut self.fronts) {
            self.recycle(front.values);
        }
        if 8 * self.panel.capacity() > budget {
            self.panel = Vec::new();
        }
        let mut left = budget.saturating_sub(8 * self.panel.capacity() + self.gathered.bytes());
        self.spare
            .sort_unstable_by_key(|buffer| std::cmp::Reverse(buffer.capacity()));
        self.spare.retain(|buffer| {
            let fits = 8 * buffer.capacity() <= left;
            if fits {
                left -= 8 * buffer.capacity();
            }
            fits
        });
    }

    /// A buffer of `len` values for an update matrix: the smallest spare that holds it, else
    /// the largest spare (grown), else a new one. What a spare held stays in it: `factor_front`
    /// writes the lower triangle of `U` without reading it, and nothing reads the rest, so
    /// zeroing it (a `memset` of up to megabytes per front) was wasted.
    fn update_buffer(&mut self, len: usize) -> Vec<f64> {
        let fits = (0..self.spare.len())
            .filter(|&i| self.spare[i].capacity() >= len)
            .min_by_key(|&i| self.spare[i].capacity());
        let largest = || (0..self.spare.len()).max_by_key(|&i| self.spare[i].capacity());
        let mut buffer = fits
            .or_else(largest)
            .map_or_else(Vec::new, |i| self.spare.swap_remove(i));
        buffer.resize(len, 0.0);
        buffer
    }

    /// Keeps `buffer` for a later front, unless as many are kept already and it is the
    /// smallest.
    fn recycle(&mut self, buffer: Vec<f64>) {
        if buffer.capacity() == 0 {
            return;
        }
        self.spare.push(buffer);
        if self.spare.len() > MAX_SPARE_BUFFERS {
            let smallest = (0..self.spare.len())
                .min_by_key(|&i| self.spare[i].capacity())
                .expect("more spares than the limit");
            self.spare.swap_remove(smallest);
        }
    }

    /// Bytes of the buffers kept between refactors.
    pub(super) fn scratch_bytes(&self) -> usize {
        let spare: usize = self.spare.iter().map(Vec::capacity).sum();
        8 * (spare + self.panel.capacity()) + self.gathered.bytes()
    }
}

/// The gathered columns of a front, copied out of the accumulator one after the other.
#[derive(Debug, Default)]
struct Gathered {
    diagonals: Vec<f64>,
    entries: Vec<(u32, u32)>,
    buffers: Vec<f64>,
    /// Per column: where its diagonal, entries and buffer start.
    starts: Vec<(usize, usize, usize)>,
}

impl Gathered {
    fn clear(&mut self) {
        self.diagonals.clear();
        self.entries.clear();
        self.buffers.clear();
        self.starts.clear();
    }

    fn bytes(&self) -> usize {
        use std::mem::size_of;
        size_of::<f64>() * (self.diagonals.capacity() + self.buffers.capacity())
            + size_of::<(u32, u32)>() * self.entries.capacity()
            + size_of::<(usize, usize, usize)>() * self.starts.capacity()
    }

    fn save(&mut self, acc: &Accumulator) {
        let (diagonal, entries, buffer) =
            (self.diagonals.len(), self.entries.len(), self.buffers.len());
        self.starts.push((diagonal, entries, buffer));
        self.diagonals.extend_from_slice(&acc.diagonal);
        self.entries.extend_from_slice(&acc.entries);
        self.buffers.extend_from_slice(&acc.buffer);
    }

    /// Column `p`: its diagonal block, its entries `(row, offset)` and the buffer they index.
    fn column(&self, p: usize) -> (&[f64], &[(u32, u32)], &[f64]) {
        let (d0, e0, b0) = self.starts[p];
        let (d1, e1, b1) = self.starts.get(p + 1).copied().unwrap_or((
            self.diagonals.len(),
            self.entries.len(),
            self.buffers.len(),
        ));
        (
            &self.diagonals[d0..d1],
            &self.entries[e0..e1],
            &self.buffers[b0..b1],
        )
    }
}

impl BlockFactor {
    /// Eliminates the front `front` (consecutive columns of the order; its first column is
    /// gathered in `acc` already, see [`front_at`]) as one dense matrix, stores its columns and
    /// keeps its update matrix for the rows beyond it.
    // Kept whole (127 lines, a written exception to the ~80-line rule): gathering the panel,
    // factoring it and storing its columns share the front's reused buffers (taken from and
    // returned to `self.fronts`) and its row map; split, each part would pass them all along.
    pub(super) fn eliminate_front<A: FnMut(usize, &[u64], &mut Accumulator)>(
        &mut self,
        front: &[usize],
        acc: &mut Accumulator,
        assemble: &mut A,
        kept_at: &mut KeptApplications,
    ) -> Result<(), NotPositiveDefinite> {
        let w = front.len();
        for (p, &r) in front.iter().enumerate() {
            self.slot[r] = p as u32;
        }
        // Each column's H entries less what was eliminated before the front; the rows beyond
        // the front (S), each with the first column of the front that reaches it.
        let mut gathered = std::mem::take(&mut self.fronts.gathered);
        gathered.clear();
        let mut beyond: Vec<(u32, usize)> = Vec::new();
        for (p, &r) in front.iter().enumerate() {
            if p > 0 {
                self.gather(r, acc, assemble, kept_at);
            }
            for &(u, _) in &acc.entries {
                if self.slot[u as usize] == NONE {
                    self.slot[u as usize] = (w + beyond.len()) as u32;
                    beyond.push((u, p));
                }
            }
            gathered.save(acc);
            acc.finish();
        }
        beyond.sort_unstable_by_key(|&(u, _)| self.rank[u as usize]);
        // The panel's rows: the front, then S in rank order.
        let panel_rows: Vec<usize> = front
            .iter()
            .copied()
            .chain(beyond.iter().map(|&(u, _)| u as usize))
            .collect();
        let mut offsets = Vec::with_capacity(panel_rows.len() + 1);
        let mut n = 0;
        for &u in &panel_rows {
            self.slot[u] = offsets.len() as u32;
            offsets.push(n);
            n += self.dim[u];
        }
        offsets.push(n);
        let nj = offsets[w];
        // The panel [A_JJ; A_SJ], column-major n × nj: entry (row a, column b) at f[b·n + a].
        let mut f = std::mem::take(&mut self.fronts.panel);
        f.clear();
        f.resize(n * nj, 0.0);
        for p in 0..w {
            let (diagonal, entries, buffer) = gathered.column(p);
            let (d, o) = (self.dim[front[p]], offsets[p]);
            for i in 0..d {
                for j in 0..=i {
                    f[(o + j) * n + o + i] = diagonal[i * d + j];
                }
            }
            for &(u, at) in entries {
                let (du, ou) = (
                    self.dim[u as usize],
                    offsets[self.slot[u as usize] as usize],
                );
                let block = &buffer[at as usize..at as usize + du * d];
                for i in 0..du {
                    for j in 0..d {
                        f[(o + j) * n + ou + i] = block[i * d + j];
                    }
                }
            }
        }
        self.fronts.gathered = gathered;
        for &u in &panel_rows {
            self.slot[u] = NONE;
        }
        let mut update = self.fronts.update_buffer((n - nj) * (n - nj));
        if let Err(row) = factor_front(&mut f, n, nj, &mut update) {
            self.fronts.panel = f;
            self.fronts.recycle(update);
            let p = offsets.partition_point(|&o| o <= row) - 1;
            return Err(NotPositiveDefinite(front[p]));
        }
        self.dense_columns += w;
        // Each column straight from the panel into its storage (cleared by the refactor).
        for (p, &r) in front.iter().enumerate() {
            let (d, o) = (self.dim[r], offsets[p]);
            let column = &mut self.columns[r];
            column.diagonal.resize(d * d, 0.0);
            for i in 0..d {
                for j in 0..=i {
                    column.diagonal[i * d + j] = f[(o + j) * n + o + i];
                }
            }
            let later_in_front = front.iter().copied().enumerate().skip(p + 1);
            let reached_beyond = beyond
                .iter()
                .enumerate()
                .filter(|(_, &(_, first))| first <= p);
            let rows = later_in_front.chain(reached_beyond.map(|(q, &(u, _))| (w + q, u as usize)));
            for (q, u) in rows {
                let (du, ou) = (self.dim[u], offsets[q]);
                let at = column.blocks.len();
                column.rows.push((u as u32, at as u32));
                column.blocks.resize(at + du * d, 0.0);
                let block = &mut column.blocks[at..];
                for j in 0..d {
                    let panel_column = &f[(o + j) * n + ou..(o + j) * n + ou + du];
                    for (i, &value) in panel_column.iter().enumerate() {
                        block[i * d + j] = value;
                    }
                }
            }
            self.register_column(r);
        }
        if !beyond.is_empty() {
            for &r in front {
                self.covered[r] = true;
                self.front_columns.push(r as u32);
            }
            let rows = beyond.iter().map(|&(u, _)| u).collect();
            let from_nj = offsets[w..].iter().map(|&o| o - nj).collect();
            self.fronts.push(rows, from_nj, update, &self.rank);
        } else {
            self.fronts.recycle(update);
        }
        self.fronts.panel = f;
        Ok(())
    }
}

/// Factors the n × nj column-major panel `[A_JJ; A_SJ]` in place into `[L_JJ; L_SJ]` (lower
/// triangles read and written) and writes `U = L_SJ L_SJᵀ` into `update` (lower triangle,
/// column-major, (n − nj)²); or returns the scalar row whose pivot failed.
fn factor_front(f: &mut [f64], n: usize, nj: usize, update: &mut [f64]) -> Result<(), usize> {
    let mut mem = MemBuffer::new(dense_llt::cholesky_in_place_scratch::<f64>(
        nj,
        Par::Seq,
        Spec::default(),
    ));
    let panel = MatMut::from_column_major_slice_mut(f, n, nj);
    let (mut top, mut bottom) = panel.split_at_row_mut(nj);
    dense_llt::cholesky_in_place(
        top.as_mut(),
        LltRegularization::default(),
        Par::Seq,
        MemStack::new(&mut mem),
        Spec::default(),
    )
    .map_err(|LltError::NonPositivePivot { index }| index)?;
    let ns = n - nj;
    if ns > 0 {
        // X Lᵀ = A_SJ  ⇔  L Xᵀ = A_SJᵀ.
        solve_lower_triangular_in_place(top.as_ref(), bottom.as_mut().transpose_mut(), Par::Seq);
        triangular_matmul::matmul(
            MatMut::from_column_major_slice_mut(update, ns, ns),
            BlockStructure::TriangularLower,
            Accum::Replace,
            bottom.as_ref(),
            BlockStructure::Rectangular,
            bottom.as_ref().transpose(),
            BlockStructure::Rectangular,
            1.0,
            Par::Seq,
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::factor_front;
    use crate::factors::testing::Rng;

    /// `factor_front` writes `U`'s lower triangle without reading it: the update buffer comes
    /// from a spare, holding whatever an earlier front left (here NaN, which any read of it
    /// would carry into the result). Sizes past faer's small-matrix kernels, so its blocked
    /// paths run.
    #[test]
    fn the_update_matrix_is_written_whole_over_stale_values() {
        let (n, nj) = (300, 120);
        let ns = n - nj;
        let mut rng = Rng::new(7);
        let m: Vec<f64> = (0..n * n).map(|_| rng.uniform() - 0.5).collect();
        // A = M Mᵀ + n I (column-major), symmetric positive definite; the panel is its first
        // nj columns.
        let a = |i: usize, j: usize| {
            let dot: f64 = (0..n).map(|k| m[i * n + k] * m[j * n + k]).sum();
            dot + if i == j { n as f64 } else { 0.0 }
        };
        let mut panel: Vec<f64> = (0..nj)
            .flat_map(|j| (0..n).map(move |i| (i, j)))
            .map(|(i, j)| a(i, j))
            .collect();
        let original = panel.clone();
        let mut update = vec![f64::NAN; ns * ns];
        factor_front(&mut panel, n, nj, &mut update).expect("positive definite");

        let l = |i: usize, j: usize| if i >= j { panel[j * n + i] } else { 0.0 };
        for j in 0..nj {
            for i in j..n {
                // [L_JJ; L_SJ] L_JJᵀ reproduces the panel's lower part.
                let product: f64 = (0..=j).map(|k| l(i, k) * l(j, k)).sum();
                let want = original[j * n + i];
                assert!(
                    (product - want).abs() <= 1e-9 * want.abs().max(1.0),
                    "({i}, {j})"
                );
            }
        }
        for j in 0..ns {
            for i in j..ns {
                let want: f64 = (0..nj).map(|k| l(nj + i, k) * l(nj + j, k)).sum();
                let got = update[j * ns + i];
                assert!(
                    (got - want).abs() <= 1e-9 * want.abs().max(1.0),
                    "U ({i}, {j}): {got}"
                );
            }
        }
    }
}
