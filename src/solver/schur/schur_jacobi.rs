//! The Schur-Jacobi preconditioner of the implicit Schur complement: the block diagonal of
//! S = U − W V⁻¹ Wᵀ, one block per reduced variable (a BAL camera: 9×9), assembled during the
//! elimination from the same W and V⁻¹ blocks as S itself would be, but only its diagonal
//! blocks: their memory grows with the cameras, not with the camera pairs. Applied by two
//! triangular solves with each block's Cholesky factor.

use super::super::cholesky::NotPositiveDefinite;
use super::super::structure::BlockPattern;
use super::eliminate::small_cholesky;

/// The block diagonal of S, then its blocks' Cholesky factors (row-major, lower triangle).
#[derive(Debug)]
pub(super) struct SchurJacobi {
    dim: Vec<usize>,
    offset: Vec<usize>,
    start: Vec<usize>,
    blocks: Vec<f64>,
}

impl SchurJacobi {
    /// Blocks of dimensions `dim` (reduced order), their first reduced rows `offset`.
    pub(super) fn new(dim: Vec<usize>, offset: Vec<usize>) -> Self {
        let mut start = Vec::with_capacity(dim.len() + 1);
        let mut len = 0;
        for d in &dim {
            start.push(len);
            len += d * d;
        }
        start.push(len);
        Self {
            dim,
            offset,
            start,
            blocks: vec![0.0; len],
        }
    }

    /// Starts a factorisation: every block is U's diagonal block (both triangles, from the lower
    /// one in `full`, where reduced block k is full position `eliminated + k`) plus `shift`
    /// (reduced rows).
    pub(super) fn reset(
        &mut self,
        full: &BlockPattern,
        values: &[f64],
        eliminated: usize,
        shift: &[f64],
    ) {
        for k in 0..self.dim.len() {
            let d = self.dim[k];
            let block = &mut self.blocks[self.start[k]..self.start[k + 1]];
            let diagonal_pair = full.column_blocks(eliminated + k)[0].1;
            for q in 0..d {
                for r in q..d {
                    let v = values[full.value_index(diagonal_pair, true, r, q)];
                    block[r * d + q] = v;
                    block[q * d + r] = v;
                }
                block[q * d + q] += shift[self.offset[k] + q];
            }
        }
    }

    /// The blocks while a factorisation subtracts from them (see [`Self::subtract`]); given
    /// back by [`Self::restore`].
    pub(super) fn take_blocks(&mut self) -> Vec<f64> {
        std::mem::take(&mut self.blocks)
    }

    pub(super) fn restore(&mut self, blocks: Vec<f64>) {
        self.blocks = blocks;
    }

    /// How many numbers the blocks take.
    pub(super) fn len(&self) -> usize {
        self.start[self.dim.len()]
    }

    /// Block k of `blocks` (laid out as this preconditioner's: its own taken out, or a thread's
    /// copy) −= W_k V⁻¹ W_kᵀ for W_k (dk × d, column-major, `w`) and V⁻¹ (d × d).
    #[inline(always)]
    pub(super) fn subtract<const D: usize, const K: usize>(
        &self,
        blocks: &mut [f64],
        k: usize,
        w: &[f64],
        v_inverse: &[f64],
        d: usize,
    ) {
        let dk = if K > 0 { K } else { self.dim[k] };
        let d = if D > 0 { D } else { d };
        let block = &mut blocks[self.start[k]..self.start[k + 1]];
        // Y = W V⁻¹ (dk × d, column-major), then block −= Y Wᵀ (lower triangle).
        let mut y = [0.0; 16 * 16];
        for t in 0..d {
            for s in 0..d {
                let factor = v_inverse[s * d + t];
                for r in 0..dk {
                    y[t * dk + r] += w[s * dk + r] * factor;
                }
            }
        }
        for r in 0..dk {
            for q in 0..=r {
                let mut acc = 0.0;
                for t in 0..d {
                    acc += y[t * dk + r] * w[t * dk + q];
                }
                block[r * dk + q] -= acc;
            }
        }
    }

    /// Factorises every block (lower triangles); a block that is not positive definite errs at
    /// its full row (`base`: the eliminated rows before the reduced ones).
    pub(super) fn factorize(&mut self, base: usize) -> Result<(), NotPositiveDefinite> {
        for k in 0..self.dim.len() {
            let d = self.dim[k];
            let block = &mut self.blocks[self.start[k]..self.start[k + 1]];
            small_cholesky(block, d).map_err(|i| NotPositiveDefinite {
                row: base + self.offset[k] + i,
            })?;
        }
        Ok(())
    }

    /// z = M⁻¹ r: per block, L Lᵀ z_k = r_k.
    pub(super) fn apply(&self, r: &[f64], z: &mut [f64]) {
        for k in 0..self.dim.len() {
            let (d, o) = (self.dim[k], self.offset[k]);
            let l = &self.blocks[self.start[k]..self.start[k + 1]];
            let z = &mut z[o..o + d];
            for i in 0..d {
                let s: f64 = (0..i).map(|j| l[i * d + j] * z[j]).sum();
                z[i] = (r[o + i] - s) / l[i * d + i];
            }
            for i in (0..d).rev() {
                let s: f64 = (i + 1..d).map(|j| l[j * d + i] * z[j]).sum();
                z[i] = (z[i] - s) / l[i * d + i];
            }
        }
    }
}
