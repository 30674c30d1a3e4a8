//! The camera-pair update of the Schur elimination on 512-bit vectors: `S_kl −= Y_k W_lᵀ` for a
//! point (3 columns) and two BAL cameras (9 rows each), the product BA's elimination spends most
//! of its time in.
//!
//! Why by hand: nine rows do not fit 256-bit vectors (4 + 4 + 1: a third of the FMAs are scalar,
//! for one row in nine), and the compiler keeps to that shape. Here rows 0–7 of each column are
//! one 512-bit vector, and row 8 of all nine columns is computed across the columns instead (W's
//! columns are contiguous over the camera's rows): 30 vector FMAs a pair where the 256-bit loop
//! issues 81 FMA instructions (54 on vectors, 27 scalar). The arithmetic is the portable kernel's, in its order (each entry `s − ((y₀w₀ +
//! y₁w₁) + y₂w₂)` with fused multiply-adds), so results are bit-identical.

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::{
    __mmask8, _mm512_fmadd_pd, _mm512_loadu_pd, _mm512_mask_storeu_pd, _mm512_maskz_loadu_pd,
    _mm512_mul_pd, _mm512_set1_pd, _mm512_storeu_pd, _mm512_sub_pd,
};

/// Rows and columns of a camera block.
const K: usize = super::CAMERA;
/// Y and W of one point's camera: `K` rows by 3 columns, column-major.
pub(super) type PointColumns = [f64; 3 * K];

/// Whether this CPU runs [`subtract_camera_product`] (detected once, then a cached load).
#[inline]
pub(super) fn available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx512f")
            && std::is_x86_feature_detected!("avx2")
            && std::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Where a 9×9 block of S lies in `s`: each column's first stored entry, and whether only the
/// lower triangle is stored (column q then starts at row q: a diagonal block of the sparse S).
pub(super) struct BlockColumns {
    pub starts: [usize; K],
    pub lower_only: bool,
}

impl BlockColumns {
    /// A block of a column-major matrix with leading dimension `n` that starts at `at` (the
    /// dense S; a diagonal block is written whole, its upper half unread).
    pub fn dense(at: usize, n: usize) -> Self {
        Self {
            starts: std::array::from_fn(|q| at + q * n),
            lower_only: false,
        }
    }
}

/// `S_block −= Y Wᵀ` for the block `columns` locates in `s` (entries not stored are neither
/// read nor written).
///
/// # Safety
/// The CPU must have AVX-512F ([`available`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
#[inline]
pub(super) unsafe fn subtract_camera_product(
    s: &mut [f64],
    columns: &BlockColumns,
    y: &PointColumns,
    w: &PointColumns,
) {
    let first_row = |q: usize| if columns.lower_only { q } else { 0 };
    // Each column's stored rows: first_row(q)..K from its start on.
    for (q, &start) in columns.starts.iter().enumerate() {
        assert!(
            start + (K - first_row(q)) <= s.len(),
            "column {q} of S's block"
        );
    }
    let s = s.as_mut_ptr();
    let (y, w) = (y.as_ptr(), w.as_ptr());
    // SAFETY (every access below): a column's stored rows lie within `s` (asserted); a lane of
    // rows 0–7 below a column's first stored row is masked off, so it is neither read nor
    // written (its address, computed with wrapping arithmetic, is never dereferenced); the
    // 8-lane loads of Y and W start at 0, 9 and 18 of 27 entries.
    unsafe {
        let y0 = _mm512_loadu_pd(y);
        let y1 = _mm512_loadu_pd(y.add(K));
        let y2 = _mm512_loadu_pd(y.add(2 * K));
        for (q, &start) in columns.starts.iter().enumerate() {
            let row0 = s.add(start).wrapping_sub(first_row(q));
            // Lanes first_row(q)..8 (none for column 8 of a lower triangle).
            let stored = (0xffu16 << first_row(q)) as __mmask8;
            let mut acc = _mm512_mul_pd(y0, _mm512_set1_pd(*w.add(q)));
            acc = _mm512_fmadd_pd(y1, _mm512_set1_pd(*w.add(K + q)), acc);
            acc = _mm512_fmadd_pd(y2, _mm512_set1_pd(*w.add(2 * K + q)), acc);
            let column = _mm512_maskz_loadu_pd(stored, row0);
            _mm512_mask_storeu_pd(row0, stored, _mm512_sub_pd(column, acc));
        }
        // Row 8 of columns 0..=7: Y[8, t] times W[0..8, t], summed over t in the same order.
        let mut row = _mm512_mul_pd(_mm512_set1_pd(*y.add(K - 1)), _mm512_loadu_pd(w));
        row = _mm512_fmadd_pd(
            _mm512_set1_pd(*y.add(2 * K - 1)),
            _mm512_loadu_pd(w.add(K)),
            row,
        );
        row = _mm512_fmadd_pd(
            _mm512_set1_pd(*y.add(3 * K - 1)),
            _mm512_loadu_pd(w.add(2 * K)),
            row,
        );
        let mut lanes = [0.0; 8];
        _mm512_storeu_pd(lanes.as_mut_ptr(), row);
        for (q, product) in lanes.iter().enumerate() {
            *s.add(columns.starts[q] + K - 1 - first_row(q)) -= product;
        }
        let mut corner = *y.add(K - 1) * *w.add(K - 1);
        corner = (*y.add(2 * K - 1)).mul_add(*w.add(2 * K - 1), corner);
        corner = (*y.add(3 * K - 1)).mul_add(*w.add(3 * K - 1), corner);
        *s.add(columns.starts[K - 1] + K - 1 - first_row(K - 1)) -= corner;
    }
}

/// Never called: [`available`] is false off x86-64.
#[cfg(not(target_arch = "x86_64"))]
pub(super) unsafe fn subtract_camera_product(
    _: &mut [f64],
    _: &BlockColumns,
    _: &PointColumns,
    _: &PointColumns,
) {
    unreachable!("no AVX-512 off x86-64")
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;

    /// The portable kernel's arithmetic, entry by entry, on the stored entries `columns`
    /// locates.
    fn reference(s: &mut [f64], columns: &BlockColumns, y: &PointColumns, w: &PointColumns) {
        for q in 0..K {
            let first = if columns.lower_only { q } else { 0 };
            for r in first..K {
                let mut acc = 0.0;
                for t in 0..3 {
                    acc = y[t * K + r].mul_add(w[t * K + q], acc);
                }
                s[columns.starts[q] + r - first] -= acc;
            }
        }
    }

    /// Whether both kernels leave `start` alike, bit for bit, and changed.
    fn check(start: &[f64], columns: &BlockColumns, y: &PointColumns, w: &PointColumns) {
        let (mut fast, mut slow) = (start.to_vec(), start.to_vec());
        // SAFETY: the caller checked `available()`.
        unsafe { subtract_camera_product(&mut fast, columns, y, w) };
        reference(&mut slow, columns, y, w);
        for (i, (a, b)) in fast.iter().zip(&slow).enumerate() {
            assert_eq!(a.to_bits(), b.to_bits(), "entry {i}: {a} against {b}");
        }
        assert_ne!(fast, start, "the block was updated");
    }

    #[test]
    fn matches_the_portable_kernel_bit_for_bit() {
        if !available() {
            eprintln!("skipped: this CPU has no AVX-512F");
            return;
        }
        let mut seed = 0x9e37_79b9_7f4a_7c15_u64;
        let mut next = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let y: PointColumns = std::array::from_fn(|_| next() * 1e3);
        let w: PointColumns = std::array::from_fn(|_| next() * 1e-2);
        // The dense S: the block at row 2, column 3 of a 13×13 column-major matrix.
        let n = 13;
        let dense: Vec<f64> = (0..n * n).map(|_| next()).collect();
        check(&dense, &BlockColumns::dense(3 * n + 2, n), &y, &w);
        // The sparse S's layouts: an off-diagonal block's columns apart, and a diagonal block's
        // lower triangle packed column after column (column q holds rows q..9), between other
        // values that must stay as they are.
        let packed: Vec<f64> = (0..100).map(|_| next()).collect();
        let apart = BlockColumns {
            starts: std::array::from_fn(|q| 3 + 10 * q),
            lower_only: false,
        };
        check(&packed, &apart, &y, &w);
        let mut at = 5;
        let lower = BlockColumns {
            starts: std::array::from_fn(|q| {
                let start = at;
                at += K - q;
                start
            }),
            lower_only: true,
        };
        // Entries outside the triangle are compared too: the reference leaves them alone.
        check(&packed, &lower, &y, &w);
    }
}
