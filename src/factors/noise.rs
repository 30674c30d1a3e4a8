//! Square-root information: `Ω = Rᵀ R` with `R` upper triangular, so `‖R e‖² = eᵀ Ω e`.

use nalgebra::DMatrix;

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum InformationError {
    #[error("information matrix is {rows}×{cols}, expected {expected}×{expected}")]
    WrongSize {
        rows: usize,
        cols: usize,
        expected: usize,
    },
    #[error("information matrix has a non-finite entry")]
    NotFinite,
    #[error("information matrix is not symmetric")]
    NotSymmetric,
    #[error("information matrix is not positive definite")]
    NotPositiveDefinite,
}

#[derive(Clone, Debug, PartialEq)]
pub struct SqrtInformation {
    dim: usize,
    /// Row-major upper-triangular `R`.
    r: Vec<f64>,
    /// `R` is diagonal (most files' information is): whitening scales rows.
    diagonal: bool,
}

impl SqrtInformation {
    /// From an information matrix `Ω`, by Cholesky `Ω = L Lᵀ`, `R = Lᵀ`.
    pub fn from_information(information: &DMatrix<f64>) -> Result<Self, InformationError> {
        let dim = information.nrows();
        if information.ncols() != dim {
            return Err(InformationError::WrongSize {
                rows: dim,
                cols: information.ncols(),
                expected: dim,
            });
        }
        if information.iter().any(|v| !v.is_finite()) {
            return Err(InformationError::NotFinite);
        }
        let scale = information.amax().max(f64::MIN_POSITIVE);
        if (information - information.transpose()).amax() > 1e-9 * scale {
            return Err(InformationError::NotSymmetric);
        }
        let chol = information
            .clone()
            .cholesky()
            .ok_or(InformationError::NotPositiveDefinite)?;
        let l = chol.l();
        // A pivot that is tiny relative to the matrix means "numerically semidefinite".
        // NaN pivots count as not positive too.
        let threshold = 1e-12 * scale.sqrt();
        if (0..dim).any(|i| l[(i, i)].partial_cmp(&threshold) != Some(std::cmp::Ordering::Greater))
        {
            return Err(InformationError::NotPositiveDefinite);
        }
        let mut r = vec![0.0; dim * dim];
        for i in 0..dim {
            for j in i..dim {
                r[i * dim + j] = l[(j, i)];
            }
        }
        Ok(Self::from_upper(dim, r))
    }

    fn from_upper(dim: usize, r: Vec<f64>) -> Self {
        let diagonal = (0..dim).all(|i| (i + 1..dim).all(|j| r[i * dim + j] == 0.0));
        Self { dim, r, diagonal }
    }

    /// Whether `R` (hence `Ω`) is diagonal.
    pub fn is_diagonal(&self) -> bool {
        self.diagonal
    }

    /// `R`, row-major upper triangular.
    pub fn upper(&self) -> &[f64] {
        &self.r
    }

    pub fn identity(dim: usize) -> Self {
        let mut r = vec![0.0; dim * dim];
        for i in 0..dim {
            r[i * dim + i] = 1.0;
        }
        Self::from_upper(dim, r)
    }

    pub fn dim(&self) -> usize {
        self.dim
    }

    /// `√w · R`: the square root of the information `w Ω` (a factor weighted by `w ≥ 0`, as
    /// graduated non-convexity weights a possibly wrong measurement).
    pub fn scaled(&self, weight: f64) -> Self {
        let root = weight.sqrt();
        Self {
            dim: self.dim,
            r: self.r.iter().map(|v| v * root).collect(),
            diagonal: self.diagonal,
        }
    }

    /// `Ω = Rᵀ R`.
    pub fn information(&self) -> DMatrix<f64> {
        let r = DMatrix::from_row_slice(self.dim, self.dim, &self.r);
        r.transpose() * r
    }

    /// `out = R e`.
    pub fn whiten_vector(&self, e: &[f64], out: &mut [f64]) {
        let d = self.dim;
        if self.diagonal {
            for i in 0..d {
                out[i] = self.r[i * d + i] * e[i];
            }
            return;
        }
        for (i, out_i) in out.iter_mut().enumerate().take(d) {
            let row = &self.r[i * d..(i + 1) * d];
            *out_i = (i..d).map(|j| row[j] * e[j]).sum();
        }
    }

    /// `out = R J` for a row-major `J` with `cols` columns.
    pub fn whiten_jacobian(&self, jacobian: &[f64], cols: usize, out: &mut [f64]) {
        let d = self.dim;
        if self.diagonal {
            for i in 0..d {
                let rii = self.r[i * d + i];
                for (o, v) in out[i * cols..(i + 1) * cols]
                    .iter_mut()
                    .zip(&jacobian[i * cols..(i + 1) * cols])
                {
                    *o = rii * v;
                }
            }
            return;
        }
        for i in 0..d {
            let out_row = &mut out[i * cols..(i + 1) * cols];
            out_row.fill(0.0);
            for j in i..d {
                let rij = self.r[i * d + j];
                if rij != 0.0 {
                    let in_row = &jacobian[j * cols..(j + 1) * cols];
                    for (o, v) in out_row.iter_mut().zip(in_row) {
                        *o += rij * v;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn whitened_norm_is_mahalanobis() {
        let omega = DMatrix::from_row_slice(3, 3, &[4.0, 1.0, 0.5, 1.0, 3.0, 0.2, 0.5, 0.2, 2.0]);
        let s = SqrtInformation::from_information(&omega).unwrap();
        let e = [0.3, -1.2, 0.7];
        let mut w = [0.0; 3];
        s.whiten_vector(&e, &mut w);
        let ev = nalgebra::DVector::from_row_slice(&e);
        let expected = (ev.transpose() * &omega * &ev)[(0, 0)];
        let got: f64 = w.iter().map(|v| v * v).sum();
        assert!((got - expected).abs() < 1e-12);
        assert!((s.information() - omega).amax() < 1e-12);
    }

    #[test]
    fn diagonal_fast_path_matches_general_whitening() {
        let diag = DMatrix::from_diagonal(&nalgebra::DVector::from_row_slice(&[4.0, 9.0, 0.25]));
        let almost =
            DMatrix::from_row_slice(3, 3, &[4.0, 1e-300, 0.0, 1e-300, 9.0, 0.0, 0.0, 0.0, 0.25]);
        let (d, g) = (
            SqrtInformation::from_information(&diag).unwrap(),
            SqrtInformation::from_information(&almost).unwrap(),
        );
        assert!(d.diagonal && !g.diagonal);
        let j: Vec<f64> = (0..12).map(|k| k as f64 * 0.7 - 3.0).collect();
        let (mut jd, mut jg) = (vec![0.0; 12], vec![0.0; 12]);
        d.whiten_jacobian(&j, 4, &mut jd);
        g.whiten_jacobian(&j, 4, &mut jg);
        assert!(jd.iter().zip(&jg).all(|(a, b)| (a - b).abs() < 1e-12));
        let (mut ed, mut eg) = ([0.0; 3], [0.0; 3]);
        d.whiten_vector(&[1.0, -2.0, 3.0], &mut ed);
        g.whiten_vector(&[1.0, -2.0, 3.0], &mut eg);
        assert_eq!(ed, [2.0, -6.0, 1.5]);
        assert!(ed.iter().zip(&eg).all(|(a, b)| (a - b).abs() < 1e-12));
    }

    #[test]
    fn rejects_bad_matrices() {
        let bad = DMatrix::from_row_slice(2, 2, &[1.0, 2.0, 2.0, 1.0]);
        assert_eq!(
            SqrtInformation::from_information(&bad),
            Err(InformationError::NotPositiveDefinite)
        );
        let nan = DMatrix::from_row_slice(2, 2, &[1.0, f64::NAN, f64::NAN, 1.0]);
        assert_eq!(
            SqrtInformation::from_information(&nan),
            Err(InformationError::NotFinite)
        );
        let zero = DMatrix::zeros(3, 3);
        assert_eq!(
            SqrtInformation::from_information(&zero),
            Err(InformationError::NotPositiveDefinite)
        );
    }
}
