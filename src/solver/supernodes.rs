//! The supernodal structure of a Cholesky factor `L`, as [`supernodal_factor`] and
//! [`supernodal_solve`] read it, and its analysis on the *block* graph.
//!
//! A supernode is a run of consecutive columns stored as one dense block, column-major: its own
//! columns (`L_top`, lower triangle used) over one row per index of its pattern (the rows below
//! it that any of its columns reaches).
//!
//! faer analyses the scalar pattern: a 2D pose graph has three scalar columns and nine scalar
//! entries per variable and block, a 3D one six and thirty-six. Every variable's columns share
//! one structure, so [`BlockSupernodes::analyze`] finds the elimination tree, the column counts
//! and the supernodes' patterns on the block graph and only then expands them to scalars. Its
//! supernodes are faer's (the same fundamental supernodes, amalgamated by faer's rule and
//! thresholds), so the numeric phase sees the same factor for a fraction of the analysis
//! (killian: ~0.1 ms, against 0.75 ms for faer's analysis and the transposed pattern it needs).
//!
//! The block steps are the textbook ones (Davis, *Direct Methods for Sparse Linear Systems*):
//! Liu's elimination tree with path compression, column counts by walking each row's subtree,
//! fundamental supernodes (a column whose only child is the column before it, with that child's
//! pattern less itself), relaxed amalgamation of each supernode into its parent when the
//! explicit zeros that adds stay under a fraction of the merged block, and each supernode's
//! pattern from the row subtrees of the supernodal tree.
//!
//! [`supernodal_factor`]: super::supernodal_factor
//! [`supernodal_solve`]: super::supernodal_solve

use std::ops::Range;

use faer::sparse::linalg::cholesky::supernodal::SymbolicSupernodalCholesky;

use super::structure::BlockPattern;

const NONE: usize = usize::MAX;

/// faer's default amalgamation rule (`SymbolicSupernodalParams::default`): a supernode merges
/// into its parent when they are adjacent and, for the first `(columns, fraction)` with
/// `columns` at least the merged width, the explicit zeros are at most `fraction` of the
/// merged block's entries.
const RELAX: [(usize, f64); 4] = [(4, 1.0), (16, 0.8), (48, 0.1), (usize::MAX, 0.05)];

/// Supernodes of `L`: columns, patterns and where each one's values start.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Supernodes {
    /// Scalar columns of supernode `s`: `begin[s]..begin[s + 1]`.
    begin: Vec<usize>,
    /// Scalar rows below supernode `s`, ascending: `rows[row_ptr[s]..row_ptr[s + 1]]`.
    row_ptr: Vec<usize>,
    rows: Vec<usize>,
    /// Supernode `s`'s dense block (columns × (columns + rows below)) is
    /// `values[value_ptr[s]..value_ptr[s + 1]]`.
    value_ptr: Vec<usize>,
}

impl Supernodes {
    pub fn count(&self) -> usize {
        self.begin.len() - 1
    }

    /// The scalar dimension of the factored matrix.
    pub fn n(&self) -> usize {
        self.begin[self.count()]
    }

    pub fn columns(&self, s: usize) -> Range<usize> {
        self.begin[s]..self.begin[s + 1]
    }

    /// The scalar rows below supernode `s`, ascending.
    pub fn pattern(&self, s: usize) -> &[usize] {
        &self.rows[self.row_ptr[s]..self.row_ptr[s + 1]]
    }

    /// Where supernode `s`'s values are: `value_ptr()[s]..value_ptr()[s + 1]`.
    pub fn value_ptr(&self) -> &[usize] {
        &self.value_ptr
    }

    /// Values of `L` stored, explicit zeros of amalgamated supernodes included.
    pub fn values_len(&self) -> usize {
        self.value_ptr[self.count()]
    }

    /// Bytes of the index arrays.
    pub fn index_bytes(&self) -> usize {
        8 * (self.begin.len() + self.row_ptr.len() + self.rows.len() + self.value_ptr.len())
    }

    /// Floating-point operations of one numeric factorisation: per supernode of c columns and
    /// r rows below it, c³/3 for its diagonal block, c²·r for the panel and c·r² for its update
    /// of the later columns.
    pub fn factor_flops(&self) -> f64 {
        (0..self.count())
            .map(|s| supernode_flops(self.columns(s).len(), self.pattern(s).len()))
            .sum()
    }

    /// Multiply-adds per stored value (see [`BlockSupernodes::flops_per_value`]).
    pub fn flops_per_value(&self) -> f64 {
        self.factor_flops() / self.values_len().max(1) as f64
    }

    /// The structure faer's symbolic analysis found (for a factor faer factorises itself).
    pub fn from_faer(symbolic: &SymbolicSupernodalCholesky<usize>) -> Self {
        let count = symbolic.n_supernodes();
        let mut begin = symbolic.supernode_begin().to_vec();
        begin.push(symbolic.supernode_end().last().copied().unwrap_or(0));
        let mut row_ptr = Vec::with_capacity(count + 1);
        let mut rows = Vec::new();
        row_ptr.push(0);
        for s in 0..count {
            rows.extend_from_slice(symbolic.supernode(s).pattern());
            row_ptr.push(rows.len());
        }
        Self {
            begin,
            row_ptr,
            rows,
            value_ptr: symbolic.col_ptr_for_val().to_vec(),
        }
    }
}

/// Supernodes in blocks, as [`BlockSupernodes::analyze`] finds them before expanding them to
/// scalars. The partition and its patterns hold for any block sizes over the same ordered
/// graph, so one analysis also serves the scalar Laplacians of the chordal start.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BlockSupernodes {
    /// First block of each supernode, then the block count.
    groups: Vec<usize>,
    /// Blocks below supernode `s`, ascending: `rows[row_ptr[s]..row_ptr[s + 1]]`.
    row_ptr: Vec<usize>,
    rows: Vec<usize>,
}

impl BlockSupernodes {
    /// The supernodes of `pattern`'s factor (`pattern` in elimination order), with faer's
    /// amalgamation for `pattern`'s block sizes.
    pub fn analyze(pattern: &BlockPattern) -> Self {
        let blocks = pattern.dim.len();
        let rows_of = lower_rows(pattern);
        let row = |k: usize| &rows_of.1[rows_of.0[k]..rows_of.0[k + 1]];
        let earlier = |k: usize| row(k).iter().copied();
        let parent = elimination_tree(blocks, earlier);
        // Rows below each block column in L, in blocks and in scalars.
        let mut below = vec![0usize; blocks];
        let mut scalars_below = vec![0usize; blocks];
        visit_factor_rows(&parent, earlier, |j, k| {
            below[j] += 1;
            scalars_below[j] += pattern.dim[k];
        });
        let groups = relaxed_groups(pattern, &parent, &below, &scalars_below);
        Self::with_groups(groups, &parent, &below, &row)
    }

    /// The supernodes whose first blocks are `groups` (ascending, ending with the block count),
    /// with their patterns from the row subtrees of the supernodal tree.
    fn with_groups<'r>(
        groups: Vec<usize>,
        parent: &[usize],
        below: &[usize],
        row: &dyn Fn(usize) -> &'r [usize],
    ) -> Self {
        let count = groups.len() - 1;
        let blocks = parent.len();
        let mut supernode_of = vec![0usize; blocks];
        for s in 0..count {
            supernode_of[groups[s]..groups[s + 1]].fill(s);
        }
        let super_parent: Vec<usize> = (0..count)
            .map(|s| match parent[groups[s + 1] - 1] {
                NONE => NONE,
                p => supernode_of[p],
            })
            .collect();
        let mut row_ptr = Vec::with_capacity(count + 1);
        row_ptr.push(0);
        for s in 0..count {
            row_ptr.push(row_ptr[s] + below[groups[s + 1] - 1]);
        }
        // Row k reaches every supernode on the tree path from those of its entries up to its
        // own; visiting k in ascending order appends each pattern in order.
        let mut rows = vec![0usize; row_ptr[count]];
        let mut cursor = row_ptr.clone();
        let mut visited = vec![NONE; count];
        for k in 0..blocks {
            visited[supernode_of[k]] = k;
            for &i in row(k) {
                let mut s = supernode_of[i];
                while visited[s] != k {
                    visited[s] = k;
                    rows[cursor[s]] = k;
                    cursor[s] += 1;
                    s = super_parent[s];
                }
            }
        }
        debug_assert_eq!(cursor[..count], row_ptr[1..]);
        Self {
            groups,
            row_ptr,
            rows,
        }
    }

    /// Multiply-adds per stored value of `pattern`'s factor on these supernodes (see
    /// [`Supernodes::factor_flops`]), without expanding them.
    pub fn flops_per_value(&self, pattern: &BlockPattern) -> f64 {
        let (mut flops, mut values) = (0.0, 0.0);
        for s in 0..self.groups.len() - 1 {
            let (first, last) = (self.groups[s], self.groups[s + 1] - 1);
            let c = pattern.offset[last] + pattern.dim[last] - pattern.offset[first];
            let below = &self.rows[self.row_ptr[s]..self.row_ptr[s + 1]];
            let r = below.iter().map(|&k| pattern.dim[k]).sum();
            flops += supernode_flops(c, r);
            values += (c * (c + r)) as f64;
        }
        if values > 0.0 {
            flops / values
        } else {
            0.0
        }
    }

    /// The scalar supernodes of `pattern`, a pattern of the graph and order analysed (its block
    /// sizes may differ).
    pub fn expand(&self, pattern: &BlockPattern) -> Supernodes {
        let count = self.groups.len() - 1;
        assert_eq!(
            self.groups[count],
            pattern.dim.len(),
            "supernodes of another block graph"
        );
        let (dim, offset) = (&pattern.dim, &pattern.offset);
        let mut begin = Vec::with_capacity(count + 1);
        let mut row_ptr = Vec::with_capacity(count + 1);
        let mut value_ptr = Vec::with_capacity(count + 1);
        let mut rows = Vec::with_capacity(self.rows.iter().map(|&k| dim[k]).sum());
        row_ptr.push(0);
        value_ptr.push(0);
        for s in 0..count {
            begin.push(offset[self.groups[s]]);
            for &k in &self.rows[self.row_ptr[s]..self.row_ptr[s + 1]] {
                rows.extend(offset[k]..offset[k] + dim[k]);
            }
            row_ptr.push(rows.len());
            let last = self.groups[s + 1] - 1;
            let columns = offset[last] + dim[last] - offset[self.groups[s]];
            let below = row_ptr[s + 1] - row_ptr[s];
            value_ptr.push(value_ptr[s] + columns * (columns + below));
        }
        begin.push(pattern.n);
        Supernodes {
            begin,
            row_ptr,
            rows,
            value_ptr,
        }
    }
}

/// Multiply-adds to factorise a supernode of `c` columns with `r` rows below it.
fn supernode_flops(c: usize, r: usize) -> f64 {
    let (c, r) = (c as f64, r as f64);
    c * c * c / 3.0 + c * c * r + c * r * r
}

/// The strictly lower block pattern by rows: for block row k, the columns i < k with a block
/// (k, i), ascending, as `(row starts, columns)`.
fn lower_rows(pattern: &BlockPattern) -> (Vec<usize>, Vec<usize>) {
    let blocks = pattern.dim.len();
    let mut starts = vec![0usize; blocks + 1];
    for b in 0..blocks {
        for &(a, _) in &pattern.column_blocks(b)[1..] {
            starts[a + 1] += 1;
        }
    }
    for k in 0..blocks {
        starts[k + 1] += starts[k];
    }
    let mut next = starts.clone();
    let mut columns = vec![0usize; starts[blocks]];
    for b in 0..blocks {
        for &(a, _) in &pattern.column_blocks(b)[1..] {
            columns[next[a]] = b;
            next[a] += 1;
        }
    }
    (starts, columns)
}

/// Liu's algorithm: the parent of each of `n` columns (`NONE` for a root), with
/// path-compressed ancestors. `earlier(k)` yields the columns adjacent to `k` (those not before
/// `k` are skipped, duplicates are harmless).
pub(crate) fn elimination_tree<I: IntoIterator<Item = usize>>(
    n: usize,
    earlier: impl Fn(usize) -> I,
) -> Vec<usize> {
    let mut parent = vec![NONE; n];
    let mut ancestor = vec![NONE; n];
    for k in 0..n {
        for mut i in earlier(k) {
            while i != NONE && i < k {
                let next = ancestor[i];
                ancestor[i] = k;
                if next == NONE {
                    parent[i] = k;
                }
                i = next;
            }
        }
    }
    parent
}

/// Calls `visit(j, k)` once for every nonzero `L[k, j]` below the diagonal of the factor: row
/// `k`'s subtree, walked up the tree `parent` from each column `earlier(k)` yields before `k`
/// until a column already visited for `k` (Davis, *Direct Methods for Sparse Linear Systems*,
/// §4.2–4.4). Time is that of the factor's nonzero count.
pub(crate) fn visit_factor_rows<I: IntoIterator<Item = usize>>(
    parent: &[usize],
    earlier: impl Fn(usize) -> I,
    mut visit: impl FnMut(usize, usize),
) {
    let mut marked_for = vec![NONE; parent.len()];
    for k in 0..parent.len() {
        marked_for[k] = k;
        for mut j in earlier(k) {
            if j > k {
                continue;
            }
            // `k` is an ancestor of every earlier neighbour, and marked: the walk ends.
            while marked_for[j] != k {
                marked_for[j] = k;
                visit(j, k);
                j = parent[j];
            }
        }
    }
}

/// The first block of every supernode (and the block count last): fundamental supernodes,
/// then each merged into the next when it is its parent and [`RELAX`] allows, as faer does.
fn relaxed_groups(
    pattern: &BlockPattern,
    parent: &[usize],
    below: &[usize],
    scalars_below: &[usize],
) -> Vec<usize> {
    let blocks = parent.len();
    if blocks == 0 {
        return vec![0];
    }
    let mut children = vec![0usize; blocks];
    for &p in parent {
        if p != NONE {
            children[p] += 1;
        }
    }
    let mut fundamental = vec![0];
    for b in 1..blocks {
        let continues = parent[b - 1] == b && children[b] == 1 && below[b - 1] == below[b] + 1;
        if !continues {
            fundamental.push(b);
        }
    }
    fundamental.push(blocks);
    let supernodes = fundamental.len() - 1;
    let last = |s: usize| fundamental[s + 1] - 1;
    let width =
        |s: usize| pattern.offset[last(s)] + pattern.dim[last(s)] - pattern.offset[fundamental[s]];
    // Merged width and explicit zeros of the group ending at each fundamental supernode.
    let mut size: Vec<usize> = (0..supernodes).map(width).collect();
    let mut zeros = vec![0usize; supernodes];
    let mut merged = vec![false; supernodes];
    for p in 1..supernodes {
        let child = p - 1;
        if !lies_in(parent[last(child)], p, &fundamental) {
            continue;
        }
        let (child_size, parent_size) = (size[child], size[p]);
        let (child_degree, parent_degree) = (scalars_below[last(child)], scalars_below[last(p)]);
        let new_zeros = (parent_size + parent_degree - child_degree) * child_size;
        let total = new_zeros + zeros[child] + zeros[p];
        let combined = child_size + parent_size;
        let entries = (combined * (combined + 1) / 2 + parent_degree * combined) as f64;
        let allowed = new_zeros == 0
            || RELAX.iter().any(|&(columns, fraction)| {
                columns >= combined && entries * fraction >= total as f64
            });
        if allowed {
            size[p] += child_size;
            zeros[p] = total;
            merged[child] = true;
        }
    }
    let mut groups: Vec<usize> = (0..supernodes)
        .filter(|&s| s == 0 || !merged[s - 1])
        .map(|s| fundamental[s])
        .collect();
    groups.push(blocks);
    groups
}

/// Whether block `b` lies in fundamental supernode `s`.
fn lies_in(b: usize, s: usize, fundamental: &[usize]) -> bool {
    b != NONE && fundamental[s] <= b && b < fundamental[s + 1]
}

#[cfg(test)]
mod tests {
    use faer::sparse::linalg::cholesky::{
        factorize_symbolic_cholesky, CholeskySymbolicParams, SymbolicCholeskyRaw, SymmetricOrdering,
    };
    use faer::sparse::linalg::SupernodalThreshold;
    use faer::sparse::SymbolicSparseColMatRef;
    use faer::Side;

    use super::super::cholesky::transpose_pattern;
    use super::*;

    /// faer's supernodal analysis of the scalar pattern, as [`Supernodes`].
    fn faer_supernodes(p: &BlockPattern) -> Supernodes {
        let params = CholeskySymbolicParams {
            supernodal_flop_ratio_threshold: SupernodalThreshold::FORCE_SUPERNODAL,
            ..Default::default()
        };
        let (col_ptr, row_idx) = transpose_pattern(p);
        let upper = SymbolicSparseColMatRef::new_checked(p.n, p.n, &col_ptr, None, &row_idx);
        let symbolic =
            factorize_symbolic_cholesky(upper, Side::Upper, SymmetricOrdering::Identity, params)
                .unwrap();
        match symbolic.raw() {
            SymbolicCholeskyRaw::Supernodal(s) => Supernodes::from_faer(s),
            SymbolicCholeskyRaw::Simplicial(_) => unreachable!("supernodal was forced"),
        }
    }

    /// The block analysis finds faer's supernodes exactly (columns, patterns, value offsets):
    /// chains with loop closures (pose graphs), grids, and random graphs, with uniform and
    /// mixed block sizes (so fundamental supernodes and every relaxation threshold occur).
    #[test]
    fn finds_faers_supernodes() {
        let mut random = crate::factors::testing::Rng::new(0x2545_f491_4f6c_dd1d);
        for case in 0..60 {
            let blocks = 1 + random.below(300);
            let mut adjacency = vec![Vec::new(); blocks];
            let link = |a: usize, b: usize, adjacency: &mut Vec<Vec<usize>>| {
                if a != b {
                    adjacency[a].push(b);
                    adjacency[b].push(a);
                }
            };
            match case % 3 {
                // A trajectory: odometry and a few loop closures.
                0 => {
                    for b in 1..blocks {
                        link(b - 1, b, &mut adjacency);
                    }
                    for _ in 0..blocks / 10 {
                        let (a, b) = (random.below(blocks), random.below(blocks));
                        link(a, b, &mut adjacency);
                    }
                }
                // A grid with some diagonals.
                1 => {
                    let side = (blocks as f64).sqrt().ceil() as usize;
                    for b in 0..blocks {
                        if b % side + 1 < side && b + 1 < blocks {
                            link(b, b + 1, &mut adjacency);
                        }
                        if b + side < blocks {
                            link(b, b + side, &mut adjacency);
                        }
                        if random.below(4) == 0 && b + side + 1 < blocks {
                            link(b, b + side + 1, &mut adjacency);
                        }
                    }
                }
                // Random edges, some blocks isolated (a forest).
                _ => {
                    for _ in 0..random.below(3 * blocks + 1) {
                        let (a, b) = (random.below(blocks), random.below(blocks));
                        link(a, b, &mut adjacency);
                    }
                }
            }
            let dims: Vec<usize> = match case % 4 {
                0 => vec![1; blocks],
                1 => vec![3; blocks],
                2 => vec![6; blocks],
                _ => (0..blocks)
                    .map(|_| [1, 2, 3, 6, 15][random.below(5)])
                    .collect(),
            };
            let p = BlockPattern::new(&dims, &adjacency);
            let blocks = BlockSupernodes::analyze(&p);
            let expanded = blocks.expand(&p);
            assert_eq!(expanded, faer_supernodes(&p), "case {case}");
            let per_value = expanded.flops_per_value();
            let estimate = blocks.flops_per_value(&p);
            assert!(
                (estimate - per_value).abs() <= 1e-9 * per_value,
                "case {case}: {estimate} vs {per_value}"
            );
        }
    }

    #[test]
    fn an_empty_pattern_has_no_supernodes() {
        let p = BlockPattern::new(&[], &[]);
        let supernodes = BlockSupernodes::analyze(&p).expand(&p);
        assert_eq!(supernodes.count(), 0);
        assert_eq!(supernodes.values_len(), 0);
    }
}
