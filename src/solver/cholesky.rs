//! Sparse Cholesky on a [`BlockPattern`]: symbolic analysis once, numeric factorisation into a
//! reused buffer every iteration, single-threaded (faster than rayon on the matrices we meet;
//! the service runs several solves in parallel instead). Sparse supernodal factors are analysed
//! on the blocks and factorised by our own loops; dense ones and simplicial ones by faer.

use dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, LltRef, SymbolicCholesky,
    SymbolicCholeskyRaw, SymmetricOrdering,
};
use faer::sparse::linalg::SupernodalThreshold;
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, MatMut, Par, Side, Spec};

use super::structure::BlockPattern;
use super::supernodal_factor::SupernodalPlan;
use super::supernodal_solve;
use super::supernodes::{BlockSupernodes, Supernodes};

/// A supernodal factor with fewer multiply-adds per stored value than this is factorised by
/// [`SupernodalPlan`]'s loops, a denser one by faer's numeric factorisation. The loops won on
/// 2D pose graphs (12–29 per value: input_INTEL_g2o 0.29 → 0.19 ms, manhattanOlson3500 1.74
/// → 1.37 ms) and lost 4–13% on 3D ones (72–330 per value), where supernodes are wider and
/// faer's blocked kernels pay.
const OWN_LOOPS_BELOW_FLOPS_PER_VALUE: f64 = 48.0;

/// The factorisation failed at a pivot: the matrix is not (numerically) positive definite there.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NotPositiveDefinite {
    /// Scalar row in elimination order.
    pub row: usize,
}

pub struct SparseCholesky {
    structure: Structure,
    l_values: Vec<f64>,
    factor_mem: MemBuffer,
    solve_mem: MemBuffer,
    /// Bytes of the two workspaces (for the memory estimate).
    workspace_bytes: usize,
    /// Scratch of [`supernodal_solve`]: one supernode's rows below it.
    below: Vec<f64>,
    factorized: bool,
}

/// Who analysed the factor and who factorises it.
enum Structure {
    /// Analysed on the blocks ([`BlockSupernodes::analyze`]), factorised by [`SupernodalPlan`]'s
    /// loops: the sparse factors of 2D graphs and of the chordal start's Laplacians.
    Own {
        supernodes: Supernodes,
        plan: SupernodalPlan,
        /// The analysis in blocks, when it was made (a forced supernodal factor).
        blocks: Option<BlockSupernodes>,
    },
    /// faer's analysis and numeric factorisation (the dense fronts of 3D graphs); solved by
    /// our loops on the same supernodes.
    FaerSupernodal {
        symbolic: SymbolicCholesky<usize>,
        supernodes: Supernodes,
    },
    /// faer's simplicial factorisation and solve.
    Simplicial(SymbolicCholesky<usize>),
}

impl std::fmt::Debug for SparseCholesky {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SparseCholesky")
            .field("kind", &self.kind())
            .field("factor_nnz", &self.l_values.len())
            .finish()
    }
}

#[derive(Debug, thiserror::Error)]
#[error("symbolic Cholesky analysis failed: {0:?}")]
pub struct SymbolicError(faer::sparse::FaerError);

impl SparseCholesky {
    /// Symbolic analysis of `pattern` (already in elimination order, lower triangle). A forced
    /// supernodal factor is analysed on the blocks ([`BlockSupernodes::analyze`]); when it is
    /// sparse enough for our loops, faer is not called at all. Otherwise faer analyses the
    /// scalar pattern and, with `AUTO`, chooses between simplicial and supernodal by its flop
    /// ratio.
    pub fn analyze(
        pattern: &BlockPattern,
        threshold: SupernodalThreshold,
    ) -> Result<Self, SymbolicError> {
        if threshold == SupernodalThreshold::FORCE_SUPERNODAL {
            let blocks = BlockSupernodes::analyze(pattern);
            if blocks.flops_per_value(pattern) < OWN_LOOPS_BELOW_FLOPS_PER_VALUE {
                return Ok(Self::own(blocks.expand(pattern), Some(blocks)));
            }
        }
        let params = CholeskySymbolicParams {
            supernodal_flop_ratio_threshold: threshold,
            ..Default::default()
        };
        // With the identity ordering faer analyses the pattern as given, and expects the upper
        // triangle; the numeric phase then takes our lower triangle directly (supernodal) or
        // transposes it itself (simplicial).
        let (col_ptr, row_idx) = transpose_pattern(pattern);
        let upper =
            SymbolicSparseColMatRef::new_checked(pattern.n, pattern.n, &col_ptr, None, &row_idx);
        let symbolic =
            factorize_symbolic_cholesky(upper, Side::Upper, SymmetricOrdering::Identity, params)
                .map_err(SymbolicError)?;
        let structure = match symbolic.raw() {
            SymbolicCholeskyRaw::Supernodal(supernodal) => {
                let supernodes = Supernodes::from_faer(supernodal);
                if supernodes.flops_per_value() < OWN_LOOPS_BELOW_FLOPS_PER_VALUE {
                    return Ok(Self::own(supernodes, None));
                }
                Structure::FaerSupernodal {
                    supernodes,
                    symbolic,
                }
            }
            SymbolicCholeskyRaw::Simplicial(_) => Structure::Simplicial(symbolic),
        };
        let factor_req = match &structure {
            Structure::FaerSupernodal { symbolic, .. } | Structure::Simplicial(symbolic) => {
                symbolic.factorize_numeric_llt_scratch::<f64>(Par::Seq, Spec::default())
            }
            Structure::Own { .. } => StackReq::empty(),
        };
        Ok(Self::with(structure, factor_req))
    }

    /// A factor of `pattern` with the supernodes another factor's analysis found in blocks
    /// (`pattern` orders the same graph the same way; its block sizes may differ), factorised by
    /// our loops. The chordal start's scalar Laplacians share the solve's analysis this way.
    pub fn with_block_supernodes(pattern: &BlockPattern, blocks: &BlockSupernodes) -> Self {
        Self::own(blocks.expand(pattern), None)
    }

    /// The analysis in blocks, when this factor was analysed that way.
    pub fn block_supernodes(&self) -> Option<&BlockSupernodes> {
        match &self.structure {
            Structure::Own { blocks, .. } => blocks.as_ref(),
            _ => None,
        }
    }

    fn own(supernodes: Supernodes, blocks: Option<BlockSupernodes>) -> Self {
        let plan = SupernodalPlan::new(&supernodes);
        let structure = Structure::Own {
            supernodes,
            plan,
            blocks,
        };
        Self::with(structure, StackReq::empty())
    }

    fn with(structure: Structure, factor_req: StackReq) -> Self {
        let (values, solve_req) = match &structure {
            Structure::Own { supernodes, .. } | Structure::FaerSupernodal { supernodes, .. } => {
                // Our own loops solve a supernodal factor: no workspace from faer.
                (supernodes.values_len(), StackReq::empty())
            }
            Structure::Simplicial(symbolic) => (
                symbolic.len_val(),
                symbolic.solve_in_place_scratch::<f64>(1, Par::Seq),
            ),
        };
        Self {
            structure,
            l_values: vec![0.0; values],
            factor_mem: MemBuffer::new(factor_req),
            solve_mem: MemBuffer::new(solve_req),
            workspace_bytes: factor_req.size_bytes() + solve_req.size_bytes(),
            below: Vec::new(),
            factorized: false,
        }
    }

    /// "supernodal" or "simplicial".
    pub fn kind(&self) -> &'static str {
        match self.structure {
            Structure::Simplicial(_) => "simplicial",
            _ => "supernodal",
        }
    }

    /// Whose code factorises: our loops on our analysis, or faer's (its supernodal or its
    /// simplicial factorisation), for the Summary's `linear_solver`.
    pub fn implementation(&self) -> &'static str {
        match self.structure {
            Structure::Own { .. } => "factord's supernodal loops",
            Structure::FaerSupernodal { .. } => "faer's supernodal",
            Structure::Simplicial(_) => "faer's simplicial",
        }
    }

    pub fn factor_nnz(&self) -> usize {
        self.l_values.len()
    }

    /// Bytes the numeric factorisation holds: L's values and indices, and the workspaces.
    pub fn numeric_bytes(&self) -> u64 {
        let indices = match &self.structure {
            Structure::Own {
                supernodes, plan, ..
            } => supernodes.index_bytes() + plan.bytes(),
            Structure::FaerSupernodal { supernodes, .. } => supernodes.index_bytes(),
            Structure::Simplicial(symbolic) => match symbolic.raw() {
                SymbolicCholeskyRaw::Simplicial(s) => 8 * (s.row_idx().len() + s.col_ptr().len()),
                SymbolicCholeskyRaw::Supernodal(_) => 0,
            },
        };
        (8 * self.l_values.len() + indices + self.workspace_bytes) as u64
    }

    /// Floating-point operations of one numeric factorisation, from the symbolic structure
    /// (see [`Supernodes::factor_flops`]; a simplicial column is a supernode of one column).
    pub fn factor_flops(&self) -> f64 {
        match &self.structure {
            Structure::Own { supernodes, .. } | Structure::FaerSupernodal { supernodes, .. } => {
                supernodes.factor_flops()
            }
            Structure::Simplicial(symbolic) => simplicial_flops(symbolic),
        }
    }

    /// Numeric LLᵀ of the matrix with `pattern` and `values`.
    pub fn factorize(
        &mut self,
        pattern: &BlockPattern,
        values: &[f64],
    ) -> Result<(), NotPositiveDefinite> {
        self.factorized = false;
        let a = SparseColMatRef::new(pattern.symbolic(), values);
        let symbolic = match &mut self.structure {
            Structure::Own {
                supernodes, plan, ..
            } => {
                plan.factorize(supernodes, a, &mut self.l_values)?;
                self.factorized = true;
                return Ok(());
            }
            Structure::FaerSupernodal { symbolic, .. } | Structure::Simplicial(symbolic) => {
                &*symbolic
            }
        };
        let stack = MemStack::new(&mut self.factor_mem);
        let result = symbolic.factorize_numeric_llt(
            &mut self.l_values,
            a,
            Side::Lower,
            LltRegularization::default(),
            Par::Seq,
            stack,
            Spec::default(),
        );
        match result {
            Ok(_) => {
                self.factorized = true;
                Ok(())
            }
            Err(faer::linalg::cholesky::llt::factor::LltError::NonPositivePivot { index }) => {
                Err(NotPositiveDefinite { row: index })
            }
        }
    }

    /// Solves `A X = B` in place for the `columns` column-major columns of `rhs` (marginal
    /// covariances solve for several unit vectors at once).
    pub fn solve_columns_in_place(&self, rhs: &mut [f64], columns: usize) {
        assert!(
            self.factorized,
            "solve before a successful factorisation is a bug"
        );
        let n = rhs.len() / columns.max(1);
        match &self.structure {
            Structure::Own { supernodes, .. } | Structure::FaerSupernodal { supernodes, .. } => {
                let mut below = Vec::new();
                for column in rhs.chunks_exact_mut(n.max(1)) {
                    supernodal_solve::solve_in_place(
                        supernodes,
                        &self.l_values,
                        column,
                        &mut below,
                    );
                }
            }
            Structure::Simplicial(symbolic) => {
                let llt = LltRef::new(symbolic, &self.l_values);
                let mut scratch =
                    MemBuffer::new(symbolic.solve_in_place_scratch::<f64>(columns, Par::Seq));
                let rhs = MatMut::from_column_major_slice_mut(rhs, n, columns);
                llt.solve_in_place_with_conj(Conj::No, rhs, Par::Seq, MemStack::new(&mut scratch));
            }
        }
    }

    /// Solves `A x = rhs` in place with the last successful factorisation.
    pub fn solve_in_place(&mut self, rhs: &mut [f64]) {
        assert!(
            self.factorized,
            "solve before a successful factorisation is a bug"
        );
        match &self.structure {
            Structure::Own { supernodes, .. } | Structure::FaerSupernodal { supernodes, .. } => {
                supernodal_solve::solve_in_place(supernodes, &self.l_values, rhs, &mut self.below);
            }
            Structure::Simplicial(symbolic) => {
                let n = rhs.len();
                let llt = LltRef::new(symbolic, &self.l_values);
                let rhs = MatMut::from_column_major_slice_mut(rhs, n, 1);
                llt.solve_in_place_with_conj(
                    Conj::No,
                    rhs,
                    Par::Seq,
                    MemStack::new(&mut self.solve_mem),
                );
            }
        }
    }
}

/// See [`SparseCholesky::factor_flops`]: a simplicial factor's columns.
fn simplicial_flops(symbolic: &SymbolicCholesky<usize>) -> f64 {
    match symbolic.raw() {
        SymbolicCholeskyRaw::Simplicial(s) => s
            .col_ptr()
            .windows(2)
            .map(|w| {
                let below = (w[1] - w[0]).saturating_sub(1) as f64;
                1.0 + 2.0 * below + below * below
            })
            .sum(),
        SymbolicCholeskyRaw::Supernodal(_) => {
            unreachable!("a simplicial structure holds faer's simplicial analysis")
        }
    }
}

/// Compressed-column pattern of the transpose (sorted rows).
pub(super) fn transpose_pattern(p: &BlockPattern) -> (Vec<usize>, Vec<usize>) {
    let mut counts = vec![0usize; p.n + 1];
    for &r in &p.row_idx {
        counts[r + 1] += 1;
    }
    for i in 0..p.n {
        counts[i + 1] += counts[i];
    }
    let mut next = counts.clone();
    let mut rows = vec![0usize; p.row_idx.len()];
    for c in 0..p.n {
        for k in p.col_ptr[c]..p.col_ptr[c + 1] {
            let r = p.row_idx[k];
            rows[next[r]] = c;
            next[r] += 1;
        }
    }
    (counts, rows)
}

#[cfg(test)]
mod tests {
    use super::super::structure::BlockOrdering;
    use super::*;

    /// Deterministic, diagonally dominant values on `p`'s pattern.
    fn values_on(p: &BlockPattern) -> Vec<f64> {
        let mut values = vec![0.0; p.nnz()];
        for c in 0..p.n {
            let column = p.col_ptr[c]..p.col_ptr[c + 1];
            for (value, &r) in values[column.clone()].iter_mut().zip(&p.row_idx[column]) {
                *value = if r == c {
                    30.0 + (c % 3) as f64
                } else {
                    ((r * 7 + c * 3) % 5) as f64 * 0.3 - 0.6
                };
            }
        }
        values
    }

    /// `chol` (analysed on `p`) factorises `values` and solves against a dense reference.
    fn assert_solves(chol: &mut SparseCholesky, p: &BlockPattern, values: &[f64]) {
        let mut dense = nalgebra::DMatrix::zeros(p.n, p.n);
        for c in 0..p.n {
            for k in p.col_ptr[c]..p.col_ptr[c + 1] {
                dense[(p.row_idx[k], c)] = values[k];
                dense[(c, p.row_idx[k])] = values[k];
            }
        }
        chol.factorize(p, values).unwrap();
        let b: Vec<f64> = (0..p.n).map(|i| (i % 7) as f64 - 3.0).collect();
        let mut x = b.clone();
        chol.solve_in_place(&mut x);
        let ax = &dense * nalgebra::DVector::from_vec(x);
        for i in 0..p.n {
            assert!((ax[i] - b[i]).abs() < 1e-10, "{} row {i}", chol.kind());
        }
    }

    #[test]
    fn solves_a_block_system() {
        let dims = [2, 3, 1, 2];
        let adjacency = vec![vec![1], vec![0, 2, 3], vec![1, 3], vec![1, 2]];
        let p = BlockPattern::new(&dims, &adjacency);
        let mut values = values_on(&p);
        let mut chol = SparseCholesky::analyze(&p, SupernodalThreshold::AUTO).unwrap();
        assert_solves(&mut chol, &p, &values);
        // An indefinite matrix is reported, not solved.
        for c in 0..p.n {
            values[p.diagonal_index(c)] = if c == 4 { -1.0 } else { 10.0 };
        }
        assert!(chol.factorize(&p, &values).is_err());
    }

    /// A 12 × 12 grid of 3-dimensional blocks with diagonals: many supernodes of several sizes
    /// with patterns below them, so the supernodal factor runs its own loops, faer's matmul for
    /// its large updates and faer's dense Cholesky for its widest supernode; the simplicial one
    /// is faer's throughout. Both against the dense reference.
    #[test]
    fn both_factorisations_solve_a_grid() {
        let side = 12;
        let blocks = side * side;
        let mut adjacency = vec![Vec::new(); blocks];
        let mut link = |a: usize, b: usize| {
            adjacency[a].push(b);
            adjacency[b].push(a);
        };
        for i in 0..side {
            for j in 0..side {
                let here = i * side + j;
                if j + 1 < side {
                    link(here, here + 1);
                }
                if i + 1 < side {
                    link(here, here + side);
                    if j + 1 < side && (i + j) % 3 == 0 {
                        link(here, here + side + 1);
                    }
                }
            }
        }
        let p = BlockPattern::new(&vec![3; blocks], &adjacency);
        let values = values_on(&p);
        for threshold in [
            SupernodalThreshold::FORCE_SUPERNODAL,
            SupernodalThreshold::FORCE_SIMPLICIAL,
        ] {
            let mut chol = SparseCholesky::analyze(&p, threshold).unwrap();
            assert_solves(&mut chol, &p, &values);
            // A negative pivot is reported at its row (the columns before it are unaffected);
            // faer's simplicial factorisation reports the row after it.
            let mut indefinite = values.clone();
            indefinite[p.diagonal_index(250)] = -1.0;
            let error = chol.factorize(&p, &indefinite).unwrap_err();
            let expected = if chol.kind() == "simplicial" {
                251
            } else {
                250
            };
            assert_eq!(error.row, expected, "{}", chol.kind());
        }
    }

    /// A factor on the supernodes another block size's analysis found (the chordal start's
    /// Laplacians on the solve's) solves as well, with that partition's explicit zeros.
    #[test]
    fn shares_a_block_analysis_across_block_sizes() {
        let side = 9;
        let blocks = side * side;
        let mut adjacency = vec![Vec::new(); blocks];
        for here in 0..blocks {
            for there in [here + 1, here + side] {
                if there < blocks && (there != here + 1 || there % side != 0) {
                    adjacency[here].push(there);
                    adjacency[there].push(here);
                }
            }
        }
        let ordering = BlockOrdering::amd(adjacency);
        let solve = BlockPattern::with_ordering(&vec![3; blocks], &ordering);
        let chol = SparseCholesky::analyze(&solve, SupernodalThreshold::FORCE_SUPERNODAL).unwrap();
        let shared = chol.block_supernodes().expect("analysed in blocks");
        let laplacian = BlockPattern::with_ordering(&vec![1; blocks], &ordering);
        let mut chol = SparseCholesky::with_block_supernodes(&laplacian, shared);
        assert_eq!(chol.kind(), "supernodal");
        assert_solves(&mut chol, &laplacian, &values_on(&laplacian));
    }
}
