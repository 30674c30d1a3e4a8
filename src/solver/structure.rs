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
    /// and for each the index of the first entry of `pair_cols` describing block (a, b).
    col_blocks: Vec<Vec<(usize, usize)>>,
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
        // Lower column blocks per elimination position.
        let mut col_lists: Vec<Vec<usize>> = (0..nb).map(|p| vec![p]).collect();
        for (i, neighbours) in adjacency.iter().enumerate() {
            let pi = position[i];
            for &j in neighbours {
                let pj = position[j];
                if pi > pj {
                    col_lists[pj].push(pi);
                }
            }
        }
        // Sized up front: BA patterns hold millions of entries, and growing by doubling costs
        // copies and page faults of the same order as a whole iteration.
        let (mut entries, mut pairs) = (0, 0);
        for (b, list) in col_lists.iter_mut().enumerate() {
            list.sort_unstable();
            list.dedup();
            let below: usize = list.iter().filter(|&&a| a != b).map(|&a| dim[a]).sum();
            entries += dim[b] * below + dim[b] * (dim[b] + 1) / 2;
            pairs += list.len() * dim[b];
        }
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::with_capacity(entries);
        let mut pair_cols = Vec::with_capacity(pairs);
        let mut col_blocks = Vec::with_capacity(nb);
        col_ptr.push(0);
        for b in 0..nb {
            let list = &col_lists[b];
            let mut blocks = Vec::with_capacity(list.len());
            let first_pair = pair_cols.len();
            for &a in list.iter() {
                blocks.push((a, pair_cols.len()));
                pair_cols.extend(std::iter::repeat_n(0, dim[b]));
            }
            for q in 0..dim[b] {
                let col_start = row_idx.len();
                // Diagonal block: rows q..dim, then every off-diagonal block whole.
                for (k, &a) in list.iter().enumerate() {
                    pair_cols[first_pair + k * dim[b] + q] = row_idx.len();
                    let first_row = if a == b { offset[b] + q } else { offset[a] };
                    row_idx.extend(first_row..offset[a] + dim[a]);
                }
                debug_assert!(row_idx.len() > col_start);
                col_ptr.push(row_idx.len());
            }
            col_blocks.push(blocks);
        }
        Self {
            position,
            block_at,
            dim,
            offset,
            n,
            col_ptr,
            row_idx,
            col_blocks,
            pair_cols,
        }
    }

    pub fn nnz(&self) -> usize {
        self.row_idx.len()
    }

    /// The lower blocks of column block `b` (elimination positions): `(a, pair)` for every `a ≥ b`
    /// in increasing order, the diagonal block first.
    pub fn column_blocks(&self, b: usize) -> &[(usize, usize)] {
        &self.col_blocks[b]
    }

    /// Index into `pair_cols` of block (a, b), a ≥ b in elimination positions.
    pub fn pair(&self, a: usize, b: usize) -> Option<usize> {
        let blocks = &self.col_blocks[b];
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
#[derive(Debug, Clone)]
pub struct BlockOrdering {
    pub adjacency: Vec<Vec<usize>>,
    pub position: Vec<usize>,
    pub block_at: Vec<usize>,
}

impl BlockOrdering {
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
    // Upper-triangular pattern with the diagonal, sorted columns.
    let mut cols: Vec<Vec<usize>> = (0..nb).map(|j| vec![j]).collect();
    for (i, neighbours) in adjacency.iter().enumerate() {
        for &j in neighbours {
            if i < j {
                cols[j].push(i);
            } else if j < i {
                cols[i].push(j);
            }
        }
    }
    let mut col_ptr = Vec::with_capacity(nb + 1);
    let mut row_idx = Vec::new();
    col_ptr.push(0);
    for c in cols.iter_mut() {
        c.sort_unstable();
        c.dedup();
        row_idx.extend_from_slice(c);
        col_ptr.push(row_idx.len());
    }
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
}
