//! The dense tail of a refactored part: once a column's rows are every column eliminated after
//! it, the rest of the refactored part is one clique (eliminating that column fills every pair
//! of its rows), which is factored as one dense matrix by faer's blocked Cholesky instead of
//! block by block. This is the root clique of iSAM2's Bayes tree (a supernode): the top
//! separators of a large map, and the ring of recent poses a 3D sphere's updates reach, where
//! the refactor spends most of its time.

use dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::{self as dense_llt, LltError, LltRegularization};
use faer::{MatMut, Par, Spec};

use super::{Accumulator, BlockFactor, KeptApplications, NotPositiveDefinite, NONE};

/// A shorter tail is eliminated column by column (the dense matrix would not pay for itself).
const MIN_COLUMNS: usize = 12;
/// A tail may start at a column that misses up to this fraction of the columns after it: those
/// blocks are stored as explicit zeros. (The newest variables, eliminated last, often reach
/// only a few of the others: a column of the clique below them misses them.)
const MAX_MISSING: f64 = 0.125;

/// Whether the dense tail starts at a column with `rows` rows, `later` columns after it.
pub(super) fn starts_here(rows: usize, later: usize) -> bool {
    later + 1 >= MIN_COLUMNS && (later - rows) as f64 <= MAX_MISSING * later as f64
}

impl BlockFactor {
    /// Eliminates `tail` (the rest of the refactored part, in order): its first column is
    /// gathered in `acc` already and reaches (nearly) every other. Each column's `H` entries
    /// less what was eliminated before the tail are gathered into one column-major matrix,
    /// factored in place, and stored back as block columns, each with a block for every
    /// column after it in the tail (zero where the clique is not complete).
    pub(super) fn eliminate_dense_tail<A: FnMut(usize, &[u64], &mut Accumulator)>(
        &mut self,
        tail: &[usize],
        acc: &mut Accumulator,
        assemble: &mut A,
        kept_at: &mut KeptApplications,
    ) -> Result<(), NotPositiveDefinite> {
        let mut offsets = Vec::with_capacity(tail.len() + 1);
        let mut n = 0;
        for (p, &r) in tail.iter().enumerate() {
            self.slot[r] = p as u32;
            offsets.push(n);
            n += self.dim[r];
        }
        offsets.push(n);
        let mut f = vec![0.0; n * n];
        for (p, &r) in tail.iter().enumerate() {
            if p > 0 {
                self.gather(r, acc, assemble, kept_at);
            }
            let (d, o) = (self.dim[r], offsets[p]);
            // Lower triangle, column-major: entry (row a ≥ column b) at f[b·n + a].
            for i in 0..d {
                for j in 0..=i {
                    f[(o + j) * n + o + i] = acc.diagonal[i * d + j];
                }
            }
            for &(u, at) in &acc.entries {
                let (du, ou) = (
                    self.dim[u as usize],
                    offsets[self.slot[u as usize] as usize],
                );
                let block = &acc.buffer[at as usize..at as usize + du * d];
                for i in 0..du {
                    for j in 0..d {
                        f[(o + j) * n + ou + i] = block[i * d + j];
                    }
                }
            }
            acc.finish();
        }
        let factored = factor_in_place(&mut f, n);
        for &r in tail {
            self.slot[r] = NONE;
        }
        if let Err(row) = factored {
            let p = offsets.partition_point(|&o| o <= row) - 1;
            return Err(NotPositiveDefinite(tail[p]));
        }
        self.dense_columns += tail.len();
        for (p, &r) in tail.iter().enumerate() {
            let (d, o) = (self.dim[r], offsets[p]);
            acc.start(d, self.dim.len());
            let diagonal = acc.diagonal_mut();
            for i in 0..d {
                for j in 0..=i {
                    diagonal[i * d + j] = f[(o + j) * n + o + i];
                }
            }
            for (q, &u) in tail.iter().enumerate().skip(p + 1) {
                let (du, ou) = (self.dim[u], offsets[q]);
                let block = acc.block_mut(u, du);
                for i in 0..du {
                    for j in 0..d {
                        block[i * d + j] = f[(o + j) * n + ou + i];
                    }
                }
            }
            self.store_column(r, acc);
        }
        Ok(())
    }
}

/// Cholesky `F = L Lᵀ` of the n×n column-major `f` (lower triangle read and overwritten), or
/// the scalar row whose pivot failed.
fn factor_in_place(f: &mut [f64], n: usize) -> Result<(), usize> {
    let mut mem = MemBuffer::new(dense_llt::cholesky_in_place_scratch::<f64>(
        n,
        Par::Seq,
        Spec::default(),
    ));
    dense_llt::cholesky_in_place(
        MatMut::from_column_major_slice_mut(f, n, n),
        LltRegularization::default(),
        Par::Seq,
        MemStack::new(&mut mem),
        Spec::default(),
    )
    .map(|_| ())
    .map_err(|LltError::NonPositivePivot { index }| index)
}
