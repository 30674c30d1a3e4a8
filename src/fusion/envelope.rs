//! The window's normal equations as an envelope (skyline) matrix and its Cholesky factor.
//!
//! The window's unknowns are its keyframes in time order. IMU, relative-pose and prior factors
//! join a keyframe to the ones just before it, so each block row of H has nonzeros only from
//! some earlier block (its *first* block) up to the diagonal. Cholesky creates no fill outside
//! that envelope (a row's first nonzero never moves left), so the factor is computed in place,
//! row by row, in the same storage: a chain of N keyframes of dimension d costs O(N d³), with
//! no ordering, no symbolic analysis and no allocation once the buffers have grown.
//!
//! Storage: row `r` keeps its columns `first[r] ..= r` contiguously, so the inner products of
//! the factorisation and of the triangular solves run over contiguous slices.

use crate::solver::vector::dot_interleaved as dot;

/// The envelope of the lower triangle of a symmetric matrix, with reusable buffers.
#[derive(Debug, Default)]
pub struct Envelope {
    /// Scalar dimension.
    n: usize,
    /// First stored column of each row.
    first: Vec<usize>,
    /// Where each row starts in `values` (n + 1 entries).
    start: Vec<usize>,
    /// The matrix's lower triangle within the envelope; the factor L after [`Envelope::factorize`].
    values: Vec<f64>,
    /// First row of each block (scratch of [`Envelope::reset`]).
    offset: Vec<usize>,
    /// The last row with an entry in each column.
    last: Vec<usize>,
}

/// The factorisation met a pivot that is not positive: the matrix is not positive definite
/// (to working precision) at this row.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct NotPositiveDefinite {
    pub row: usize,
}

impl Envelope {
    /// Lays out the envelope of blocks of dimensions `dims` where block `p`'s row starts at
    /// block `first_block[p]` (≤ p), and zeroes it. Keeps the buffers' capacity.
    pub fn reset(&mut self, dims: &[usize], first_block: &[usize]) {
        debug_assert_eq!(dims.len(), first_block.len());
        let mut offset = std::mem::take(&mut self.offset);
        offset.clear();
        let mut n = 0;
        for &d in dims {
            offset.push(n);
            n += d;
        }
        self.n = n;
        self.first.clear();
        self.start.clear();
        self.start.push(0);
        let mut len = 0;
        for (p, &d) in dims.iter().enumerate() {
            debug_assert!(first_block[p] <= p);
            let f = offset[first_block[p]];
            for i in 0..d {
                let r = offset[p] + i;
                self.first.push(f);
                len += r - f + 1;
                self.start.push(len);
            }
        }
        self.values.clear();
        self.values.resize(len, 0.0);
        self.offset = offset;
        // Rows reaching back to column c at most: a running maximum over the rows' first columns.
        self.last.clear();
        self.last.extend(0..n);
        for r in 0..n {
            let f = self.first[r];
            self.last[f] = self.last[f].max(r);
        }
        for c in 1..n {
            self.last[c] = self.last[c].max(self.last[c - 1]);
        }
    }

    /// Zeroes the matrix, keeping its envelope.
    pub fn clear(&mut self) {
        self.values.fill(0.0);
    }

    pub fn n(&self) -> usize {
        self.n
    }

    /// Stored values of row `r`, from column `first(r)` to the diagonal.
    #[inline]
    pub fn row_mut(&mut self, r: usize) -> &mut [f64] {
        &mut self.values[self.start[r]..self.start[r + 1]]
    }

    #[inline]
    pub fn first(&self, r: usize) -> usize {
        self.first[r]
    }

    /// Adds `v` to entry (r, c) of the lower triangle (c ≤ r, inside the envelope).
    #[inline]
    pub fn add(&mut self, r: usize, c: usize, v: f64) {
        debug_assert!(c <= r && c >= self.first[r]);
        self.values[self.start[r] + c - self.first[r]] += v;
    }

    /// Entry (r, c) of the lower triangle, zero outside the envelope.
    pub fn get(&self, r: usize, c: usize) -> f64 {
        let (r, c) = if c > r { (c, r) } else { (r, c) };
        if c < self.first[r] {
            0.0
        } else {
            self.values[self.start[r] + c - self.first[r]]
        }
    }

    /// Adds `shift` to every diagonal entry.
    pub fn shift_diagonal(&mut self, shift: f64) {
        for r in 0..self.n {
            let i = self.start[r + 1] - 1;
            self.values[i] += shift;
        }
    }

    /// Replaces the matrix by its Cholesky factor L (A = L Lᵀ) in place.
    pub fn factorize(&mut self) -> Result<(), NotPositiveDefinite> {
        #[cfg(target_arch = "x86_64")]
        if crate::solver::simd::has_wide_vectors() {
            // SAFETY: the CPU has the features `factorize_wide` is compiled for.
            return unsafe { self.factorize_wide() };
        }
        self.factorize_with()
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn factorize_wide(&mut self) -> Result<(), NotPositiveDefinite> {
        self.factorize_with()
    }

    /// Left-looking by columns: column j's diagonal from row j (done), then every entry below
    /// it independently of the others (no chain of dependent divisions along a row).
    #[inline(always)]
    fn factorize_with(&mut self) -> Result<(), NotPositiveDefinite> {
        for j in 0..self.n {
            let (fj, sj, ej) = (self.first[j], self.start[j], self.start[j + 1]);
            let (head, tail) = self.values.split_at_mut(ej);
            let row_j = &mut head[sj..];
            let (off, diag) = row_j.split_at_mut(j - fj);
            let d = diag[0] - dot(off, off);
            if !(d > 0.0 && d.is_finite()) {
                return Err(NotPositiveDefinite { row: j });
            }
            let ljj = d.sqrt();
            diag[0] = ljj;
            let inverse = 1.0 / ljj;
            let row_j = &head[sj..];
            for i in j + 1..=self.last[j] {
                let fi = self.first[i];
                if fi > j {
                    continue;
                }
                let k0 = fi.max(fj);
                let si = self.start[i] - ej;
                let row_i = &mut tail[si..si + i - fi + 1];
                let s = row_i[j - fi] - dot(&row_i[k0 - fi..j - fi], &row_j[k0 - fj..j - fj]);
                row_i[j - fi] = s * inverse;
            }
        }
        Ok(())
    }

    /// Solves L Lᵀ x = rhs in place with the factor of [`Envelope::factorize`].
    pub fn solve_in_place(&self, x: &mut [f64]) {
        debug_assert_eq!(x.len(), self.n);
        for i in 0..self.n {
            let fi = self.first[i];
            let row = &self.values[self.start[i]..self.start[i + 1]];
            let s = x[i] - dot(&row[..i - fi], &x[fi..i]);
            x[i] = s / row[i - fi];
        }
        for i in (0..self.n).rev() {
            let fi = self.first[i];
            let row = &self.values[self.start[i]..self.start[i + 1]];
            x[i] /= row[i - fi];
            let xi = x[i];
            for (xk, l) in x[fi..i].iter_mut().zip(&row[..i - fi]) {
                *xk -= l * xi;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{DMatrix, DVector};

    /// A random symmetric positive definite matrix with the envelope of `first_block`.
    fn banded(dims: &[usize], first_block: &[usize], seed: u64) -> (Envelope, DMatrix<f64>) {
        let mut env = Envelope::default();
        env.reset(dims, first_block);
        let n = env.n();
        let mut state = seed;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        let mut dense = DMatrix::zeros(n, n);
        for r in 0..n {
            for c in env.first(r)..r {
                let v = next();
                env.add(r, c, v);
                dense[(r, c)] = v;
                dense[(c, r)] = v;
            }
        }
        // Diagonally dominant: positive definite.
        for r in 0..n {
            let v = n as f64 + next();
            env.add(r, r, v);
            dense[(r, r)] = v;
        }
        (env, dense)
    }

    #[test]
    fn solves_like_a_dense_cholesky() {
        // A chain with one longer link (block 4 reaches back to block 1).
        let dims = [3, 2, 4, 3, 2];
        let first = [0, 0, 1, 2, 1];
        let (mut env, dense) = banded(&dims, &first, 7);
        let n = env.n();
        assert_eq!(env.get(n - 1, 0), 0.0);
        let rhs = DVector::from_iterator(n, (0..n).map(|i| (i as f64).sin()));
        let expected = dense.clone().cholesky().unwrap().solve(&rhs);
        env.factorize().unwrap();
        let mut x = rhs.as_slice().to_vec();
        env.solve_in_place(&mut x);
        let error = (DVector::from_vec(x) - &expected).amax();
        assert!(error < 1e-12, "{error}");
    }

    #[test]
    fn refuses_an_indefinite_matrix() {
        let mut env = Envelope::default();
        env.reset(&[2], &[0]);
        env.add(0, 0, 1.0);
        env.add(1, 0, 2.0);
        env.add(1, 1, 1.0);
        assert_eq!(env.factorize(), Err(NotPositiveDefinite { row: 1 }));
    }
}
