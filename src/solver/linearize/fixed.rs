//! The per-factor part of linearisation in fixed-size arithmetic for the common shapes (a pose
//! graph's 3×6 and 6×12 between factors, their 3×3 and 6×6 priors, a BAL reprojection's 2×12):
//! whitening `R e`, `R J`, chi2, and the factor's own `JᵀJ` (both triangles) and `Jᵀr`. With the
//! sizes known at compile time the loops unroll into registers; the generic loops of
//! [`super::chunk`] cost several times more per factor on small shapes. Same operations in the same order, so the
//! results are those of the generic path.

use crate::factors::SqrtInformation;

use super::BlockPattern;

/// Whitens `e` (D) and `jac` (D × C, row-major) by `sqrt`, writes the factor's `JᵀJ` into
/// `gram[..C * C]` and `Jᵀr` into `gradient[..C]`, returns ‖R e‖². No robust kernel.
#[inline(always)]
pub(super) fn whitened_gram<const D: usize, const C: usize, const HESSIAN: bool>(
    sqrt: &SqrtInformation,
    e: &[f64],
    jac: &[f64],
    gram: &mut [f64],
    gradient: &mut [f64],
) -> f64 {
    let upper = &sqrt.upper()[..D * D];
    let (e, jac) = (&e[..D], &jac[..D * C]);
    let mut r = [0.0f64; D];
    let mut wj = [[0.0f64; C]; D];
    if sqrt.is_diagonal() {
        for i in 0..D {
            let rii = upper[i * D + i];
            r[i] = rii * e[i];
            for c in 0..C {
                wj[i][c] = rii * jac[i * C + c];
            }
        }
    } else {
        for i in 0..D {
            for j in i..D {
                let rij = upper[i * D + j];
                r[i] += rij * e[j];
                if rij != 0.0 {
                    for c in 0..C {
                        wj[i][c] += rij * jac[j * C + c];
                    }
                }
            }
        }
    }
    let mut chi2 = 0.0;
    for v in r {
        chi2 += v * v;
    }
    let mut grad = [0.0f64; C];
    for k in 0..D {
        for i in 0..C {
            grad[i] += wj[k][i] * r[k];
        }
    }
    if HESSIAN {
        let mut g = [[0.0f64; C]; C];
        for row in &wj {
            for i in 0..C {
                for j in 0..C {
                    g[i][j] += row[i] * row[j];
                }
            }
        }
        for (row, out) in g.iter().zip(gram[..C * C].chunks_exact_mut(C)) {
            out.copy_from_slice(row);
        }
    }
    gradient[..C].copy_from_slice(&grad);
    chi2
}

/// [`whitened_gram`] for the shapes it is compiled for; `None` for any other. Without
/// `HESSIAN` only `gradient` is written.
#[inline(always)]
pub(super) fn whitened_gram_fixed<const HESSIAN: bool>(
    sqrt: &SqrtInformation,
    d: usize,
    cols: usize,
    e: &[f64],
    jac: &[f64],
    gram: &mut [f64],
    gradient: &mut [f64],
) -> Option<f64> {
    if sqrt.dim() != d {
        return None;
    }
    Some(match (d, cols) {
        (3, 6) => whitened_gram::<3, 6, HESSIAN>(sqrt, e, jac, gram, gradient),
        (3, 3) => whitened_gram::<3, 3, HESSIAN>(sqrt, e, jac, gram, gradient),
        (6, 12) => whitened_gram::<6, 12, HESSIAN>(sqrt, e, jac, gram, gradient),
        (6, 6) => whitened_gram::<6, 6, HESSIAN>(sqrt, e, jac, gram, gradient),
        // A reprojection: a 2-pixel residual on a BAL camera (9) and a point (3).
        (2, 12) => whitened_gram::<2, 12, HESSIAN>(sqrt, e, jac, gram, gradient),
        _ => return None,
    })
}

/// Adds the factor's `JᵀJ` block of local columns `ci..ci+R` × `cj..cj+C` (`gram` has `cols`
/// columns) into H's block `pair` of R×C variables; a diagonal block (R = C) only its lower
/// triangle. `h` holds H's values from value index `first` on.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(super) fn scatter_block<const R: usize, const C: usize>(
    pattern: &BlockPattern,
    h: &mut [f64],
    first: usize,
    pair: usize,
    diagonal: bool,
    gram: &[f64],
    cols: usize,
    ci: usize,
    cj: usize,
) {
    for q in 0..C {
        let rows = if diagonal { q } else { 0 };
        let base = pattern.value_index(pair, diagonal, rows, q) - first;
        // Column cj + q of the symmetric gram is its row: contiguous over the rows.
        let source = &gram[(cj + q) * cols + ci + rows..(cj + q) * cols + ci + R];
        if diagonal {
            add_exact(&mut h[base..base + R - rows], source);
        } else if let (Some(t), Some(s)) =
            (h[base..].first_chunk_mut::<R>(), source.first_chunk::<R>())
        {
            for i in 0..R {
                t[i] += s[i];
            }
        }
    }
}

/// `target += source` for slices of equal length up to 6 with the length known at compile
/// time: a loop of runtime length vectorises with masked loads and stores, which stalled the
/// scatter on short columns (a third of a small pose graph's linearisation).
#[inline(always)]
pub(super) fn add_exact(target: &mut [f64], source: &[f64]) {
    add_scaled_exact(target, source, 1.0);
}

/// `target += sign · source` as [`add_exact`] (`sign` ±1, so exactly `±source`).
#[inline(always)]
pub(super) fn add_scaled_exact(target: &mut [f64], source: &[f64], sign: f64) {
    match target.len() {
        1 => add_n::<1>(target, source, sign),
        2 => add_n::<2>(target, source, sign),
        3 => add_n::<3>(target, source, sign),
        4 => add_n::<4>(target, source, sign),
        5 => add_n::<5>(target, source, sign),
        6 => add_n::<6>(target, source, sign),
        _ => {
            for (t, s) in target.iter_mut().zip(source) {
                *t += sign * s;
            }
        }
    }
}

#[inline(always)]
fn add_n<const L: usize>(target: &mut [f64], source: &[f64], sign: f64) {
    if let (Some(t), Some(s)) = (target.first_chunk_mut::<L>(), source.first_chunk::<L>()) {
        for i in 0..L {
            t[i] += sign * s[i];
        }
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::DMatrix;

    use super::*;

    /// The fixed-size kernel against the plain definitions `r = R e`, `JᵀJ`, `Jᵀr` with
    /// `J = R J₀`, for a correlated and a diagonal information.
    #[test]
    fn whitened_gram_matches_the_definition() {
        let correlated =
            DMatrix::from_row_slice(3, 3, &[50.0, 10.0, 2.0, 10.0, 30.0, 1.0, 2.0, 1.0, 400.0]);
        let diagonal = DMatrix::from_diagonal(&nalgebra::DVector::from_vec(vec![4.0, 9.0, 25.0]));
        for information in [correlated, diagonal] {
            let sqrt = SqrtInformation::from_information(&information).unwrap();
            let e = [0.3, -1.2, 0.7];
            let jac: Vec<f64> = (0..18)
                .map(|k| ((k * 7 % 11) as f64 - 5.0) * 0.37)
                .collect();
            let (mut gram, mut gradient) = (vec![0.0; 36], vec![0.0; 6]);
            let chi2 = whitened_gram_fixed::<true>(&sqrt, 3, 6, &e, &jac, &mut gram, &mut gradient)
                .expect("3×6 is a fixed shape");
            let r = DMatrix::from_row_slice(3, 3, sqrt.upper());
            let whitened_e = &r * DMatrix::from_row_slice(3, 1, &e);
            let whitened_j = &r * DMatrix::from_row_slice(3, 6, &jac);
            let expected_gram = whitened_j.transpose() * &whitened_j;
            let expected_gradient = whitened_j.transpose() * &whitened_e;
            assert!((chi2 - whitened_e.norm_squared()).abs() < 1e-9 * chi2);
            for i in 0..6 {
                assert!((gradient[i] - expected_gradient[i]).abs() < 1e-9);
                for j in 0..6 {
                    assert!((gram[i * 6 + j] - expected_gram[(i, j)]).abs() < 1e-9);
                }
            }
        }
        let sqrt = SqrtInformation::identity(3);
        let mut scratch = vec![0.0; 64];
        let mut gradient = vec![0.0; 8];
        assert!(whitened_gram_fixed::<true>(
            &sqrt,
            3,
            5,
            &[0.0; 3],
            &[0.0; 15],
            &mut scratch,
            &mut gradient
        )
        .is_none());
    }
}
