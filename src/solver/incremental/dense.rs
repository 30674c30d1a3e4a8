//! Small dense kernels on the blocks of the incremental factor (row-major, dimensions 1–15):
//! triangular solves with a diagonal block (its Cholesky is the Schur complement's
//! `small_cholesky`), and the `C −= A·Bᵀ` update that
//! left-looking elimination spends its time in.

/// `acc (m×d) −= a (m×k) · bᵀ` with `b` d×k; all row-major. The block sizes of 2D and 3D pose
/// graphs get loops of constant length (unrolled: this is where elimination spends its time).
/// `FUSED`: the constant-size products as fused multiply-adds, for callers compiled with FMA
/// (see `solver::simd`; without it `mul_add` is a library call).
#[inline(always)]
pub fn sub_mul_transpose<const FUSED: bool>(
    acc: &mut [f64],
    a: &[f64],
    b: &[f64],
    m: usize,
    d: usize,
    k: usize,
) {
    match (m, d, k) {
        (3, 3, 3) => sub_mul_transpose_fixed::<3, 3, 3, FUSED>(acc, a, b),
        (6, 6, 6) => sub_mul_transpose_fixed::<6, 6, 6, FUSED>(acc, a, b),
        _ => sub_mul_transpose_any(acc, a, b, m, d, k),
    }
}

/// As [`sub_mul_transpose`] for constant sizes: `b` transposed once, then each row of the
/// product accumulated as `Σ_l a_il · bᵀ_l` over contiguous rows (vectorises over `j`).
#[inline(always)]
fn sub_mul_transpose_fixed<const M: usize, const D: usize, const K: usize, const FUSED: bool>(
    acc: &mut [f64],
    a: &[f64],
    b: &[f64],
) {
    let (acc, a, b) = (&mut acc[..M * D], &a[..M * K], &b[..D * K]);
    let mut bt = [[0.0; D]; K];
    for j in 0..D {
        for l in 0..K {
            bt[l][j] = b[j * K + l];
        }
    }
    for i in 0..M {
        let mut row = [0.0; D];
        for l in 0..K {
            let a_il = a[i * K + l];
            for j in 0..D {
                row[j] = if FUSED {
                    a_il.mul_add(bt[l][j], row[j])
                } else {
                    row[j] + a_il * bt[l][j]
                };
            }
        }
        for j in 0..D {
            acc[i * D + j] -= row[j];
        }
    }
}

fn sub_mul_transpose_any(acc: &mut [f64], a: &[f64], b: &[f64], m: usize, d: usize, k: usize) {
    debug_assert!(acc.len() >= m * d && a.len() >= m * k && b.len() >= d * k);
    for i in 0..m {
        let ai = &a[i * k..(i + 1) * k];
        let row = &mut acc[i * d..(i + 1) * d];
        for (j, out) in row.iter_mut().enumerate() {
            let bj = &b[j * k..(j + 1) * k];
            let mut s = 0.0;
            for l in 0..k {
                s += ai[l] * bj[l];
            }
            *out -= s;
        }
    }
}

/// `y (m) −= a (m×k) · x (k)`; the square blocks of 2D and 3D poses get constant lengths (the
/// solves walk every block of the columns they visit).
#[inline]
pub fn sub_mul_vector(y: &mut [f64], a: &[f64], x: &[f64], m: usize, k: usize) {
    match (m, k) {
        (3, 3) => sub_mul_vector_fixed::<3, 3>(y, a, x),
        (6, 6) => sub_mul_vector_fixed::<6, 6>(y, a, x),
        _ => sub_mul_vector_any(y, a, x, m, k),
    }
}

#[inline(always)]
fn sub_mul_vector_fixed<const M: usize, const K: usize>(y: &mut [f64], a: &[f64], x: &[f64]) {
    sub_mul_vector_any(&mut y[..M], &a[..M * K], &x[..K], M, K)
}

#[inline(always)]
fn sub_mul_vector_any(y: &mut [f64], a: &[f64], x: &[f64], m: usize, k: usize) {
    for (i, yi) in y.iter_mut().enumerate().take(m) {
        let ai = &a[i * k..(i + 1) * k];
        *yi -= ai.iter().zip(x).map(|(p, q)| p * q).sum::<f64>();
    }
}

/// `y (k) −= aᵀ · x` with `a` m×k (constant lengths as in [`sub_mul_vector`]).
#[inline]
pub fn sub_mul_transpose_vector(y: &mut [f64], a: &[f64], x: &[f64], m: usize, k: usize) {
    match (m, k) {
        (3, 3) => sub_mul_transpose_vector_any(&mut y[..3], &a[..9], &x[..3], 3, 3),
        (6, 6) => sub_mul_transpose_vector_fixed::<6, 6>(y, a, x),
        _ => sub_mul_transpose_vector_any(y, a, x, m, k),
    }
}

/// The sum is taken in a local array and subtracted once: written into `y` term by term, the
/// compiler (inlined into back substitution, where it cannot tell `y` from `a` and `x` apart)
/// stored `y` after every product and ran the products one scalar at a time. (sphere2500's
/// back substitution: 3.3–3.5 → 3.0–3.1 s. The 3×3 blocks of 2D poses keep the plain loop:
/// summed this way, the 10k graph's first 6 000 poses took 1.03–1.21 s of back substitution
/// against 0.91–1.07 s.)
#[inline(always)]
fn sub_mul_transpose_vector_fixed<const M: usize, const K: usize>(
    y: &mut [f64],
    a: &[f64],
    x: &[f64],
) {
    let (a, x) = (&a[..M * K], &x[..M]);
    let mut sum = [0.0; K];
    for (ai, &xi) in a.chunks_exact(K).zip(x) {
        for (s, &aij) in sum.iter_mut().zip(ai) {
            *s += aij * xi;
        }
    }
    for (yj, s) in y[..K].iter_mut().zip(sum) {
        *yj -= s;
    }
}

#[inline(always)]
fn sub_mul_transpose_vector_any(y: &mut [f64], a: &[f64], x: &[f64], m: usize, k: usize) {
    for (i, &xi) in x.iter().enumerate().take(m) {
        let ai = &a[i * k..(i + 1) * k];
        for (yj, &aij) in y.iter_mut().zip(ai) {
            *yj -= aij * xi;
        }
    }
}

/// `z ← L⁻¹ z` for the lower-triangular d×d `l`.
#[inline]
pub fn forward(l: &[f64], z: &mut [f64], d: usize) {
    for i in 0..d {
        let mut s = z[i];
        for k in 0..i {
            s -= l[i * d + k] * z[k];
        }
        z[i] = s / l[i * d + i];
    }
}

/// `z ← L⁻ᵀ z` for the lower-triangular d×d `l`.
#[inline]
pub fn backward(l: &[f64], z: &mut [f64], d: usize) {
    for i in (0..d).rev() {
        let mut s = z[i];
        for k in i + 1..d {
            s -= l[k * d + i] * z[k];
        }
        z[i] = s / l[i * d + i];
    }
}

/// `−L⁻¹` (row-major) of the lower-triangular d×d `l`, into `out`.
pub fn negated_lower_inverse(l: &[f64], d: usize, out: &mut Vec<f64>) {
    out.clear();
    out.resize(d * d, 0.0);
    let mut column = vec![0.0; d];
    for j in 0..d {
        column.fill(0.0);
        column[j] = -1.0;
        forward(l, &mut column, d);
        for i in 0..d {
            out[i * d + j] = column[i];
        }
    }
}

/// `x (m×d) ← x · L⁻ᵀ` given `negated_inverse = −L⁻¹` (see [`negated_lower_inverse`]): one
/// product instead of a triangular solve per row (`scratch` holds a copy of `x`). `FUSED` as
/// in [`sub_mul_transpose`].
#[inline(always)]
pub fn times_inverse_transpose<const FUSED: bool>(
    x: &mut [f64],
    negated_inverse: &[f64],
    m: usize,
    d: usize,
    scratch: &mut Vec<f64>,
) {
    scratch.clear();
    scratch.extend_from_slice(&x[..m * d]);
    x[..m * d].fill(0.0);
    sub_mul_transpose::<FUSED>(x, scratch, negated_inverse, m, d, d);
}

/// `x (m×d) ← x · L⁻ᵀ`: each row `xᵢ` becomes the solution of `L zᵀ = xᵢᵀ` (the reference
/// [`times_inverse_transpose`] is tested against).
#[cfg(test)]
pub fn solve_right_transpose(x: &mut [f64], l: &[f64], m: usize, d: usize) {
    for row in x.chunks_exact_mut(d).take(m) {
        forward(l, row, d);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solver::schur::small_cholesky;

    #[test]
    fn cholesky_and_solves_agree_with_nalgebra() {
        let d = 4;
        let m = nalgebra::DMatrix::<f64>::from_fn(d, d, |i, j| ((i * 3 + j * 5) % 7) as f64 - 3.0);
        let spd = &m * m.transpose() + nalgebra::DMatrix::identity(d, d) * 2.0;
        let mut a: Vec<f64> = (0..d * d).map(|k| spd[(k / d, k % d)]).collect();
        small_cholesky(&mut a, d).unwrap();
        let l = nalgebra::DMatrix::from_row_slice(d, d, &a).lower_triangle();
        assert!((&l * l.transpose() - &spd).norm() < 1e-10);
        let b = [1.0, -2.0, 0.5, 3.0];
        let mut z = b;
        forward(&a, &mut z, d);
        backward(&a, &mut z, d);
        let x = spd
            .clone()
            .cholesky()
            .unwrap()
            .solve(&nalgebra::DVector::from_row_slice(&b));
        for i in 0..d {
            assert!((z[i] - x[i]).abs() < 1e-10);
        }
        // x · L⁻ᵀ · Lᵀ = x.
        let mut rows = vec![1.0, 2.0, 3.0, 4.0, -1.0, 0.0, 2.0, 1.0];
        solve_right_transpose(&mut rows, &a, 2, d);
        let back = nalgebra::DMatrix::from_row_slice(2, d, &rows) * l.transpose();
        assert!((back[(1, 2)] - 2.0).abs() < 1e-10 && (back[(0, 3)] - 4.0).abs() < 1e-10);
        let (mut inverse, mut scratch) = (Vec::new(), Vec::new());
        negated_lower_inverse(&a, d, &mut inverse);
        let mut rows2 = vec![1.0, 2.0, 3.0, 4.0, -1.0, 0.0, 2.0, 1.0];
        times_inverse_transpose::<false>(&mut rows2, &inverse, 2, d, &mut scratch);
        for (p, q) in rows.iter().zip(&rows2) {
            assert!((p - q).abs() < 1e-12);
        }
        let mut indefinite = vec![1.0, 0.0, 2.0, 1.0];
        assert_eq!(small_cholesky(&mut indefinite, 2), Err(1));
    }

    #[test]
    fn updates_match_the_products() {
        let (m, d, k) = (2, 3, 2);
        let a = [1.0, 2.0, 3.0, 4.0];
        let b = [1.0, 0.0, 0.0, 1.0, 1.0, 1.0];
        let mut acc = vec![0.0; m * d];
        sub_mul_transpose::<false>(&mut acc, &a, &b, m, d, k);
        assert_eq!(acc, vec![-1.0, -2.0, -3.0, -3.0, -4.0, -7.0]);
        let mut y = [0.0, 0.0];
        sub_mul_vector(&mut y, &a, &[1.0, 1.0], m, k);
        assert_eq!(y, [-3.0, -7.0]);
        let mut z = [0.0, 0.0];
        sub_mul_transpose_vector(&mut z, &a, &[1.0, 1.0], m, k);
        assert_eq!(z, [-4.0, -6.0]);
    }

    #[test]
    fn the_fixed_size_products_match_nalgebra() {
        // The 3×3 and 6×6 blocks take their own paths; each must equal y − aᵀx, y − a·x and
        // c − a·bᵀ.
        for d in [3, 6] {
            let a =
                nalgebra::DMatrix::<f64>::from_fn(d, d, |i, j| ((i * 5 + j * 3) % 11) as f64 - 4.5);
            let x = nalgebra::DVector::<f64>::from_fn(d, |i, _| i as f64 * 0.5 - 1.0);
            let y = nalgebra::DVector::<f64>::from_fn(d, |i, _| (i * i) as f64);
            let row_major: Vec<f64> = (0..d * d).map(|p| a[(p / d, p % d)]).collect();
            let mut transposed = y.as_slice().to_vec();
            sub_mul_transpose_vector(&mut transposed, &row_major, x.as_slice(), d, d);
            let mut straight = y.as_slice().to_vec();
            sub_mul_vector(&mut straight, &row_major, x.as_slice(), d, d);
            let (expected_t, expected) = (&y - a.transpose() * &x, &y - &a * &x);
            for i in 0..d {
                assert!(
                    (transposed[i] - expected_t[i]).abs() < 1e-12,
                    "d = {d}, row {i}"
                );
                assert!(
                    (straight[i] - expected[i]).abs() < 1e-12,
                    "d = {d}, row {i}"
                );
            }
            // C − A·Bᵀ, with the products fused and not.
            let b = nalgebra::DMatrix::<f64>::from_fn(d, d, |i, j| ((i * 7 + j) % 5) as f64 - 2.0);
            let b_row_major: Vec<f64> = (0..d * d).map(|p| b[(p / d, p % d)]).collect();
            let expected = &a - &a * b.transpose();
            for fused in [false, true] {
                let mut acc = row_major.clone();
                if fused {
                    sub_mul_transpose::<true>(&mut acc, &row_major, &b_row_major, d, d, d);
                } else {
                    sub_mul_transpose::<false>(&mut acc, &row_major, &b_row_major, d, d, d);
                }
                for p in 0..d * d {
                    assert!(
                        (acc[p] - expected[(p / d, p % d)]).abs() < 1e-12,
                        "d = {d}, fused {fused}, entry {p}"
                    );
                }
            }
        }
    }
}
