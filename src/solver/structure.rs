//! The block sparsity pattern of the normal equations, computed once per problem structure.
//!
//! Variables are blocks. The fill-reducing ordering is computed on the *block* graph (AMD), which
//! is several times smaller than the scalar graph and keeps every block's columns contiguous, so
//! supernodes line up with variables. The matrix is then laid out directly in that order as the
//! lower triangle in compressed-column form, which is exactly what faer's supernodal Cholesky
//! consumes: no permutation or transposition happens per factorisation.

use dyn_stack::{MemBuffer, MemStack};
use faer::sparse::linalg::amd;
use faer::sparse::SymbolicSparseColMatRef;

/// Whether a [`BlockPattern`] lists the scalar row of every value (as many `usize` as H has
/// values): a sparse Cholesky of the whole pattern ([`BlockPattern::symbolic`]) and Dogleg's
/// scalar product read them; the Schur complement addresses H by blocks and does without (a
/// bundle adjustment's W blocks make them about a sixth of its peak memory, and listing them
/// costs as much as a linearisation's page faults).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ScalarRows {
    Listed,
    Omitted,
}

/// A lower-triangular block-sparse symmetric pattern in elimination order.
#[derive(Debug, Clone)]
pub struct BlockPattern {
    /// Elimination position of each original block.
    pub position: Vec<usize>,
    /// Original block at each elimination position.
    pub block_at: Vec<usize>,
    /// Scalar dimension and first scalar row of each block, indexed by elimination position.
    pub dim: Vec<usize>,
    pub offset: Vec<usize>,
    pub n: usize,
    pub col_ptr: Vec<usize>,
    pub row_idx: Vec<usize>,
    /// For each elimination position `b`: the sorted positions `a ≥ b` of its lower column blocks,
    /// and for each the index of the first entry of `pair_cols` describing block (a, b); column
    /// block `b`'s entries are `col_blocks[col_block_ptr[b]..col_block_ptr[b + 1]]`.
    col_block_ptr: Vec<usize>,
    col_blocks: Vec<(usize, usize)>,
    /// For block pair (a, b) with first entry `p`: `pair_cols[p + q]` is the value index of
    /// element (first row of a, column q of b) — or, on a diagonal block, of (row q, column q).
    pair_cols: Vec<usize>,
}

impl BlockPattern {
    /// `dims[i]` is the dimension of original block `i`; `adjacency[i]` lists the blocks it shares
    /// a factor with (either direction, duplicates allowed).
    pub fn new(dims: &[usize], adjacency: &[Vec<usize>]) -> Self {
        Self::with_ordering(dims, &BlockOrdering::amd(adjacency.to_vec()))
    }

    /// As [`BlockPattern::new`] for a graph ordered earlier (the ordering carries its graph).
    pub fn with_ordering(dims: &[usize], ordering: &BlockOrdering) -> Self {
        Self::with_ordering_rows(dims, ordering, ScalarRows::Listed)
    }

    /// [`Self::with_ordering`], listing the scalar row of every value only when `rows` asks
    /// (see [`ScalarRows`]).
    pub fn with_ordering_rows(dims: &[usize], ordering: &BlockOrdering, rows: ScalarRows) -> Self {
        let nb = dims.len();
        assert_eq!(
            ordering.position.len(),
            nb,
            "ordering is for another block graph"
        );
        let adjacency = &ordering.adjacency;
        let (position, block_at) = (ordering.position.clone(), ordering.block_at.clone());
        let mut dim = vec![0; nb];
        let mut offset = vec![0; nb];
        let mut n = 0;
        for (p, &b) in block_at.iter().enumerate() {
            dim[p] = dims[b];
            offset[p] = n;
            n += dims[b];
        }
        let LowerBlocks {
            below_start,
            below,
            below_len,
        } = LowerBlocks::new(adjacency, &position, &block_at);
        let lower = |b: usize| {
            std::iter::once(b).chain(
                below[below_start[b]..below_start[b] + below_len[b]]
                    .iter()
                    .copied(),
            )
        };
        // Sized up front: BA patterns hold millions of entries, and growing by doubling costs
        // copies and page faults of the same order as a whole iteration.
        let (mut entries, mut pairs, mut blocks_total) = (0, 0, 0);
        for b in 0..nb {
            let below_dims: usize = lower(b).skip(1).map(|a| dim[a]).sum();
            entries += dim[b] * below_dims + dim[b] * (dim[b] + 1) / 2;
            pairs += (below_len[b] + 1) * dim[b];
            blocks_total += below_len[b] + 1;
        }
        let mut col_ptr = Vec::with_capacity(n + 1);
        let listed = rows == ScalarRows::Listed;
        let mut row_idx = Vec::with_capacity(if listed { entries } else { 0 });
        // Values laid out so far: the length `row_idx` has, or would have when not listed.
        let mut values = 0;
        let mut pair_cols = Vec::with_capacity(pairs);
        let mut col_blocks = Vec::with_capacity(blocks_total);
        let mut col_block_ptr = Vec::with_capacity(nb + 1);
        col_ptr.push(0);
        col_block_ptr.push(0);
        for b in 0..nb {
            let first_pair = pair_cols.len();
            for a in lower(b) {
                col_blocks.push((a, pair_cols.len()));
                pair_cols.extend(std::iter::repeat_n(0, dim[b]));
            }
            col_block_ptr.push(col_blocks.len());
            if dim[b] == 0 {
                continue;
            }
            // The block's first column: the diagonal block's rows, then every off-diagonal block
            // whole. Its column q is that column less its first q rows, copied.
            let first = values;
            for (k, a) in lower(b).enumerate() {
                pair_cols[first_pair + k * dim[b]] = values;
                if listed {
                    row_idx.extend(offset[a]..offset[a] + dim[a]);
                }
                values += dim[a];
            }
            let end = values;
            col_ptr.push(end);
            let blocks_here = col_block_ptr[b + 1] - col_block_ptr[b];
            for q in 1..dim[b] {
                let start = values;
                if listed {
                    row_idx.extend_from_within(first + q..end);
                }
                values += end - (first + q);
                pair_cols[first_pair + q] = start;
                for k in 1..blocks_here {
                    let in_first = pair_cols[first_pair + k * dim[b]] - first;
                    pair_cols[first_pair + k * dim[b] + q] = start + in_first - q;
                }
                col_ptr.push(values);
            }
        }
        Self {
            position,
            block_at,
            dim,
            offset,
            n,
            col_ptr,
            row_idx,
            col_block_ptr,
            col_blocks,
            pair_cols,
        }
    }

    pub fn nnz(&self) -> usize {
        self.col_ptr[self.col_ptr.len() - 1]
    }

    /// Whether the scalar row indices are listed (see [`ScalarRows`]).
    pub fn has_scalar_rows(&self) -> bool {
        self.row_idx.len() == self.nnz()
    }

    /// The lower blocks of column block `b` (elimination positions): `(a, pair)` for every `a ≥ b`
    /// in increasing order, the diagonal block first.
    pub fn column_blocks(&self, b: usize) -> &[(usize, usize)] {
        &self.col_blocks[self.col_block_ptr[b]..self.col_block_ptr[b + 1]]
    }

    /// Index into `pair_cols` of block (a, b), a ≥ b in elimination positions.
    pub fn pair(&self, a: usize, b: usize) -> Option<usize> {
        let blocks = self.column_blocks(b);
        blocks
            .binary_search_by_key(&a, |&(row, _)| row)
            .ok()
            .map(|k| blocks[k].1)
    }

    /// Value index of element (row r of block a, column q of block b) for a pair found by
    /// [`BlockPattern::pair`]; on a diagonal block only r ≥ q is stored.
    #[inline]
    pub fn value_index(&self, pair: usize, diagonal: bool, r: usize, q: usize) -> usize {
        self.pair_cols[pair + q] + if diagonal { r - q } else { r }
    }

    /// Value index of the diagonal element of scalar column `c`.
    #[inline]
    pub fn diagonal_index(&self, c: usize) -> usize {
        self.col_ptr[c]
    }

    pub fn symbolic(&self) -> SymbolicSparseColMatRef<'_, usize> {
        assert!(
            self.has_scalar_rows(),
            "the pattern's scalar rows were forgotten"
        );
        // SAFETY: `with_ordering` builds `col_ptr` non-decreasing from 0 to `row_idx.len()`, and
        // each column's rows strictly increasing and < n (diagonal block rows, then whole blocks
        // in sorted block order); `pattern_covers_every_pair_once` checks this, and debug builds
        // re-check it on every call. Checking on every factorisation cost ~1% of a solve.
        debug_assert!({
            SymbolicSparseColMatRef::new_checked(
                self.n,
                self.n,
                &self.col_ptr,
                None,
                &self.row_idx,
            );
            true
        });
        unsafe {
            SymbolicSparseColMatRef::new_unchecked(
                self.n,
                self.n,
                &self.col_ptr,
                None,
                &self.row_idx,
            )
        }
    }

    /// The block (elimination position) holding scalar row `row`.
    pub fn block_of_row(&self, row: usize) -> usize {
        match self.offset.binary_search(&row) {
            Ok(p) => p,
            Err(p) => p - 1,
        }
    }
}

/// A block graph and an elimination order of it: `position[block]` and its inverse
/// `block_at[position]`. Built once per solve and shared by every system over that graph.
#[derive(Debug, Clone, Default)]
pub struct BlockOrdering {
    pub adjacency: Vec<Vec<usize>>,
    pub position: Vec<usize>,
    pub block_at: Vec<usize>,
}

impl BlockOrdering {
    /// The block at each position of AMD's order of `adjacency`, for a caller that needs
    /// neither the graph kept nor the inverse permutation (no copy of the graph is made).
    pub fn amd_order(adjacency: &[Vec<usize>]) -> Vec<usize> {
        block_amd(adjacency).1
    }

    /// Approximate minimum degree on the block graph `adjacency`.
    pub fn amd(adjacency: Vec<Vec<usize>>) -> Self {
        let (position, block_at) = block_amd(&adjacency);
        Self {
            adjacency,
            position,
            block_at,
        }
    }
}

/// AMD on the block graph. Returns (position of each block, block at each position).
fn block_amd(adjacency: &[Vec<usize>]) -> (Vec<usize>, Vec<usize>) {
    let nb = adjacency.len();
    let identity = || ((0..nb).collect::<Vec<_>>(), (0..nb).collect::<Vec<_>>());
    if nb <= 2 {
        return identity();
    }
    // Upper-triangular pattern with the diagonal, sorted columns without duplicates, in flat
    // arrays (one Vec per block cost more than the ordering on small pose graphs).
    let mut col_ptr = vec![0usize; nb + 1];
    for (i, neighbours) in adjacency.iter().enumerate() {
        for &j in neighbours {
            if j != i {
                col_ptr[i.max(j) + 1] += 1;
            }
        }
    }
    for j in 0..nb {
        col_ptr[j + 1] += col_ptr[j] + 1;
    }
    let mut row_idx = vec![0usize; col_ptr[nb]];
    let mut len = vec![0usize; nb];
    for (i, neighbours) in adjacency.iter().enumerate() {
        for &j in neighbours {
            if j != i {
                let (row, col) = (i.min(j), i.max(j));
                row_idx[col_ptr[col] + len[col]] = row;
                len[col] += 1;
            }
        }
    }
    // Compact: sort and deduplicate each column's rows, then its diagonal last.
    let mut write = 0;
    let mut start = 0;
    for j in 0..nb {
        let column = &mut row_idx[start..start + len[j]];
        column.sort_unstable();
        let end = col_ptr[j + 1];
        let mut last = None;
        for k in start..start + len[j] {
            let r = row_idx[k];
            if last != Some(r) {
                row_idx[write] = r;
                write += 1;
                last = Some(r);
            }
        }
        row_idx[write] = j;
        write += 1;
        start = end;
        col_ptr[j + 1] = write;
    }
    row_idx.truncate(write);
    let pattern = SymbolicSparseColMatRef::new_checked(nb, nb, &col_ptr, None, &row_idx);
    let mut fwd = vec![0usize; nb];
    let mut inv = vec![0usize; nb];
    let mut mem = MemBuffer::new(amd::order_scratch::<usize>(nb, row_idx.len()));
    match amd::order(
        &mut fwd,
        &mut inv,
        pattern,
        amd::Control::default(),
        MemStack::new(&mut mem),
    ) {
        // fwd[new] = old, inv[old] = new.
        Ok(_) => (inv, fwd),
        Err(_) => identity(),
    }
}

/// The blocks below the diagonal in each block column of the factor (elimination positions),
/// sorted and without duplicates, in one flat array: column `b`'s are
/// `below[below_start[b]..below_start[b] + below_len[b]]`.
struct LowerBlocks {
    below_start: Vec<usize>,
    below: Vec<usize>,
    below_len: Vec<usize>,
}

impl LowerBlocks {
    /// Visiting the rows in elimination order appends each row to a column in increasing order,
    /// so a repeated (row, column) pair is always the column's last entry. (Assumes each edge
    /// is listed from both ends, as `adjacency` is.)
    fn new(adjacency: &[Vec<usize>], position: &[usize], block_at: &[usize]) -> Self {
        let nb = position.len();
        let mut below_start = vec![0usize; nb + 1];
        for (i, neighbours) in adjacency.iter().enumerate() {
            let pi = position[i];
            for &j in neighbours {
                if pi > position[j] {
                    below_start[position[j] + 1] += 1;
                }
            }
        }
        for b in 0..nb {
            below_start[b + 1] += below_start[b];
        }
        let mut below = vec![0usize; below_start[nb]];
        let mut below_len = vec![0usize; nb];
        for (pi, &i) in block_at.iter().enumerate() {
            for &j in &adjacency[i] {
                let pj = position[j];
                if pj < pi {
                    let (s, l) = (below_start[pj], below_len[pj]);
                    if l == 0 || below[s + l - 1] != pi {
                        below[s + l] = pi;
                        below_len[pj] += 1;
                    }
                }
            }
        }
        Self {
            below_start,
            below,
            below_len,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pattern_covers_every_pair_once() {
        // A chain 0-1-2-3 with a loop 3-0, blocks of mixed size.
        let dims = [3, 2, 3, 1];
        let adjacency = vec![vec![1, 3], vec![0, 2], vec![1, 3], vec![2, 0]];
        let p = BlockPattern::new(&dims, &adjacency);
        assert_eq!(p.n, 9);
        let mut seen = vec![false; p.nnz()];
        for (i, nb) in adjacency.iter().enumerate() {
            for &j in nb.iter().chain(std::iter::once(&i)) {
                let (a, b) = (
                    p.position[i].max(p.position[j]),
                    p.position[i].min(p.position[j]),
                );
                let pair = p.pair(a, b).expect("pair present");
                for q in 0..p.dim[b] {
                    let rows = if a == b { q..p.dim[a] } else { 0..p.dim[a] };
                    for r in rows {
                        let idx = p.value_index(pair, a == b, r, q);
                        assert_eq!(p.row_idx[idx], p.offset[a] + r);
                        assert!(
                            idx >= p.col_ptr[p.offset[b] + q]
                                && idx < p.col_ptr[p.offset[b] + q + 1]
                        );
                        seen[idx] = true;
                    }
                }
            }
        }
        assert!(seen.iter().all(|&s| s));
        for c in 0..p.n {
            assert_eq!(p.row_idx[p.diagonal_index(c)], c);
        }
    }

    /// Without its scalar rows a pattern addresses every value where the listed one does.
    #[test]
    fn omitted_scalar_rows_change_no_address() {
        let dims = [3, 2, 3, 1, 9];
        let adjacency = vec![
            vec![1, 3, 4],
            vec![0, 2],
            vec![1, 3, 4],
            vec![2, 0],
            vec![0, 2],
        ];
        let ordering = BlockOrdering::amd(adjacency.clone());
        let listed = BlockPattern::with_ordering_rows(&dims, &ordering, ScalarRows::Listed);
        let omitted = BlockPattern::with_ordering_rows(&dims, &ordering, ScalarRows::Omitted);
        assert!(listed.has_scalar_rows() && !omitted.has_scalar_rows());
        assert!(omitted.row_idx.is_empty());
        assert_eq!(
            (&omitted.col_ptr, &omitted.pair_cols, &omitted.col_blocks),
            (&listed.col_ptr, &listed.pair_cols, &listed.col_blocks)
        );
    }
}
