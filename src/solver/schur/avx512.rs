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
    _mm512_fmadd_pd, _mm512_loadu_pd, _mm512_mul_pd, _mm512_set1_pd, _mm512_storeu_pd,
    _mm512_sub_pd,
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

/// `S[0..9, 0..9] −= Y Wᵀ`: `s` holds the block column-major with leading dimension `n`
/// (`s[q·n + r]` is row r of column q; the dense reduced system). The whole block is written,
/// as the portable kernel writes it.
///
/// # Safety
/// The CPU must have AVX-512F ([`available`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
#[inline]
pub(super) unsafe fn subtract_camera_product(
    s: &mut [f64],
    n: usize,
    y: &PointColumns,
    w: &PointColumns,
) {
    assert!(n >= K && s.len() > (K - 1) * n + K - 1, "a 9×9 block of S");
    let s = s.as_mut_ptr();
    let (y, w) = (y.as_ptr(), w.as_ptr());
    // SAFETY (every pointer below): rows 0..=8 of columns 0..=8 lie within `s` (asserted), and
    // the 8-lane loads of Y and W start at 0, 9 and 18 of 27 entries.
    unsafe {
        let y0 = _mm512_loadu_pd(y);
        let y1 = _mm512_loadu_pd(y.add(K));
        let y2 = _mm512_loadu_pd(y.add(2 * K));
        for q in 0..K {
            let column = s.add(q * n);
            let mut acc = _mm512_mul_pd(y0, _mm512_set1_pd(*w.add(q)));
            acc = _mm512_fmadd_pd(y1, _mm512_set1_pd(*w.add(K + q)), acc);
            acc = _mm512_fmadd_pd(y2, _mm512_set1_pd(*w.add(2 * K + q)), acc);
            _mm512_storeu_pd(column, _mm512_sub_pd(_mm512_loadu_pd(column), acc));
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
            *s.add(q * n + K - 1) -= product;
        }
        let mut corner = *y.add(K - 1) * *w.add(K - 1);
        corner = (*y.add(2 * K - 1)).mul_add(*w.add(2 * K - 1), corner);
        corner = (*y.add(3 * K - 1)).mul_add(*w.add(3 * K - 1), corner);
        *s.add((K - 1) * n + K - 1) -= corner;
    }
}

/// Never called: [`available`] is false off x86-64.
#[cfg(not(target_arch = "x86_64"))]
pub(super) unsafe fn subtract_camera_product(
    _: &mut [f64],
    _: usize,
    _: &PointColumns,
    _: &PointColumns,
) {
    unreachable!("no AVX-512 off x86-64")
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;

    /// The portable kernel's arithmetic, entry by entry.
    fn reference(s: &mut [f64], n: usize, y: &PointColumns, w: &PointColumns) {
        for q in 0..K {
            for r in 0..K {
                let mut acc = 0.0;
                for t in 0..3 {
                    acc = y[t * K + r].mul_add(w[t * K + q], acc);
                }
                s[q * n + r] -= acc;
            }
        }
    }

    #[test]
    fn matches_the_portable_kernel_bit_for_bit() {
        if !available() {
            eprintln!("skipped: this CPU has no AVX-512F");
            return;
        }
        let n = 13;
        let mut seed = 0x9e37_79b9_7f4a_7c15_u64;
        let mut next = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let y: PointColumns = std::array::from_fn(|_| next() * 1e3);
        let w: PointColumns = std::array::from_fn(|_| next() * 1e-2);
        let start: Vec<f64> = (0..n * n).map(|_| next()).collect();
        let (mut fast, mut slow) = (start.clone(), start.clone());
        // The block at row 2, column 3 of a 13×13 column-major S.
        let at = 3 * n + 2;
        // SAFETY: `available()` said the CPU has the features.
        unsafe { subtract_camera_product(&mut fast[at..], n, &y, &w) };
        reference(&mut slow[at..], n, &y, &w);
        for (i, (a, b)) in fast.iter().zip(&slow).enumerate() {
            assert_eq!(a.to_bits(), b.to_bits(), "entry {i}: {a} against {b}");
        }
        assert_ne!(fast, start, "the block was updated");
    }
}
