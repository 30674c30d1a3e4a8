//! Marginal covariances of selected variables from one sparse Cholesky factorisation of the
//! Gauss-Newton Hessian at the current estimate, without ever forming H⁻¹.
//!
//! With H = JᵀΩJ (robust weights included, no damping) factorised once as L Lᵀ in the fill-reducing
//! order, the joint covariance of a set of variables with tangent columns E is Eᵀ H⁻¹ E: one solve
//! per selected tangent direction (three for an SE(2) pose), each O(nnz(L)). This is what GTSAM's
//! `Marginals` computes (it factorises at the values it is given, too) and what g2o's
//! `computeMarginals` does with its solver's factor.
//!
//! Covariances are in each variable's tangent space as its retraction defines it (`se2`: additive
//! world-frame x, y and θ as g2o; `se3`: body-frame translation then rotation). The gauge is
//! removed as the solver removes it: variables the solve holds fixed (by the client or as a
//! component's anchor) have zero covariance, and the others are conditioned on them. A problem
//! with a free gauge (bundle adjustment without priors) has a singular H, and says so.

use std::collections::HashMap;
use std::time::Instant;

use faer::sparse::linalg::SupernodalThreshold;

use super::cholesky::SparseCholesky;
use super::gauge::anchor_components;
use super::linearize::{linearize, Scratch, SystemLayout};
use super::SolverError;
use crate::problem::{Gauge, Key, Problem};

/// A factorisation of H at one estimate, ready to answer covariance queries.
#[derive(Debug)]
pub struct Marginals {
    cholesky: SparseCholesky,
    n: usize,
    /// Per variable key: its tangent dimension and, when free, its first row in H.
    rows: HashMap<Key, (usize, Option<usize>)>,
    /// Variables held fixed in the factorised system (client-fixed and gauge anchors).
    pub gauge_fixed: Vec<Key>,
    pub factorize_seconds: f64,
}

/// The joint marginal covariance of the variables asked for, in the order asked.
#[derive(Clone, Debug, PartialEq)]
pub struct Covariance {
    pub keys: Vec<Key>,
    pub dims: Vec<usize>,
    /// Row-major, `Σdims × Σdims`.
    pub joint: Vec<f64>,
}

impl Marginals {
    /// Bytes this factorisation holds (counted in its session's `memory_bytes`).
    pub fn memory_bytes(&self) -> u64 {
        const ENTRY: u64 = 48; // key, dimension, row, and the map's overhead
        self.cholesky.numeric_bytes()
            + ENTRY * self.rows.len() as u64
            + 8 * self.gauge_fixed.len() as u64
    }
}

impl Covariance {
    pub fn dimension(&self) -> usize {
        self.dims.iter().sum()
    }

    /// The `dims[a] × dims[b]` block between the `a`-th and `b`-th variables, row-major.
    pub fn block(&self, a: usize, b: usize) -> Vec<f64> {
        let n = self.dimension();
        let start = |i: usize| self.dims[..i].iter().sum::<usize>();
        let (ra, cb) = (start(a), start(b));
        let mut out = Vec::with_capacity(self.dims[a] * self.dims[b]);
        for r in ra..ra + self.dims[a] {
            out.extend_from_slice(&self.joint[r * n + cb..r * n + cb + self.dims[b]]);
        }
        out
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MarginalsError {
    #[error("unknown variable {key}")]
    UnknownVariable { key: Key },
    #[error("variable {key} is asked for twice")]
    Repeated { key: Key },
}

impl Marginals {
    /// Linearises `problem` at its current values and factorises H.
    pub fn new(problem: &Problem) -> Result<Self, SolverError> {
        let start = Instant::now();
        let values = &problem.values;
        let (fixed, gauge_fixed) = match problem.gauge {
            Gauge::AnchorComponents => anchor_components(problem.factors(), values),
            Gauge::Free => (
                (0..values.len()).map(|v| values.is_fixed(v)).collect(),
                Vec::new(),
            ),
        };
        let layout = SystemLayout::new(problem.factors(), values, &fixed);
        let n = layout.n();
        let mut h = vec![0.0; layout.pattern.nnz()];
        let mut b = vec![0.0; n];
        let mut scratch = Scratch::new(&layout);
        linearize(
            problem.factors(),
            values,
            &layout,
            &mut scratch,
            &mut h,
            &mut b,
        )?;
        let mut cholesky =
            SparseCholesky::analyze(&layout.pattern, SupernodalThreshold::FORCE_SUPERNODAL)?;
        if let Err(e) = cholesky.factorize(&layout.pattern, &h) {
            let key = layout.key_at_row(values, e.row);
            return Err(SolverError::IndeterminateSystem { keys: vec![key] });
        }
        let rows = (0..values.len())
            .map(|v| {
                let dim = values.variable(v).tangent_dim();
                let row = layout.position_of_var[v].map(|p| layout.pattern.offset[p]);
                (values.key(v), (dim, row))
            })
            .collect();
        let mut gauge_fixed: Vec<Key> = gauge_fixed;
        gauge_fixed.extend(
            (0..values.len())
                .filter(|&v| values.is_fixed(v))
                .map(|v| values.key(v)),
        );
        gauge_fixed.sort_unstable();
        gauge_fixed.dedup();
        Ok(Self {
            cholesky,
            n,
            rows,
            gauge_fixed,
            factorize_seconds: start.elapsed().as_secs_f64(),
        })
    }

    /// Whether `key` is a variable of the factorised problem.
    pub fn contains(&self, key: Key) -> bool {
        self.rows.contains_key(&key)
    }

    /// The joint covariance of `keys`: one solve of L Lᵀ x = e per free tangent direction.
    pub fn covariance(&self, keys: &[Key]) -> Result<Covariance, MarginalsError> {
        let mut dims = Vec::with_capacity(keys.len());
        let mut rows = Vec::with_capacity(keys.len());
        for (i, &key) in keys.iter().enumerate() {
            if keys[..i].contains(&key) {
                return Err(MarginalsError::Repeated { key });
            }
            let &(dim, row) = self
                .rows
                .get(&key)
                .ok_or(MarginalsError::UnknownVariable { key })?;
            dims.push(dim);
            rows.push(row);
        }
        let total: usize = dims.iter().sum();
        // One right-hand side per free tangent direction, solved together.
        let mut directions = Vec::new(); // (joint column, row of H)
        let mut col = 0;
        for (&dim, row) in dims.iter().zip(&rows) {
            if let Some(row) = row {
                directions.extend((0..dim).map(|d| (col + d, row + d)));
            }
            col += dim;
        }
        let n = self.n;
        let mut columns = vec![0.0; n * directions.len()];
        for (c, &(_, row)) in directions.iter().enumerate() {
            columns[c * n + row] = 1.0;
        }
        if !directions.is_empty() {
            self.cholesky
                .solve_columns_in_place(&mut columns, directions.len());
        }
        let mut joint = vec![0.0; total * total];
        for (c, &(joint_col, _)) in directions.iter().enumerate() {
            let column = &columns[c * n..(c + 1) * n];
            // Column `joint_col` of the joint matrix: the rows of every selected free variable.
            for &(joint_row, row) in &directions {
                joint[joint_row * total + joint_col] = column[row];
            }
        }
        // H⁻¹ is symmetric; the solves agree to rounding. Symmetrise so clients get an exact one.
        for i in 0..total {
            for j in 0..i {
                let m = 0.5 * (joint[i * total + j] + joint[j * total + i]);
                joint[i * total + j] = m;
                joint[j * total + i] = m;
            }
        }
        Ok(Covariance {
            keys: keys.to_vec(),
            dims,
            joint,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::{BetweenSe2, PriorSe2};
    use crate::geometry::Se2;
    use nalgebra::{DMatrix, Matrix3};

    /// A loop of four SE(2) poses with one prior; H is small enough to invert densely.
    fn square() -> Problem {
        let mut p = Problem::new();
        let guesses = [
            (0.0, 0.0, 0.0),
            (1.1, 0.1, 1.5),
            (0.9, 1.0, 3.0),
            (-0.1, 1.1, -1.6),
        ];
        for (k, &(x, y, t)) in guesses.iter().enumerate() {
            p.add_variable(k as Key, Box::new(Se2::new(x, y, t)))
                .unwrap();
        }
        let info = Matrix3::new(50.0, 2.0, 0.0, 2.0, 40.0, 1.0, 0.0, 1.0, 200.0);
        let step = Se2::new(1.0, 0.0, std::f64::consts::FRAC_PI_2);
        for k in 0..4u64 {
            p.add_factor(
                Box::new(BetweenSe2::new(k, (k + 1) % 4, step)),
                &DMatrix::from_column_slice(3, 3, info.as_slice()),
                None,
                format!("edge {k}"),
            )
            .unwrap();
        }
        p.add_factor(
            Box::new(PriorSe2::new(0, Se2::new(0.0, 0.0, 0.0))),
            &DMatrix::from_diagonal_element(3, 3, 1e4),
            None,
            "prior",
        )
        .unwrap();
        p
    }

    /// H from the same linearisation, densified and inverted: the reference.
    fn dense_inverse(problem: &Problem) -> (DMatrix<f64>, SystemLayout) {
        let fixed = vec![false; problem.values.len()];
        let layout = SystemLayout::new(problem.factors(), &problem.values, &fixed);
        let n = layout.n();
        let mut h = vec![0.0; layout.pattern.nnz()];
        let mut b = vec![0.0; n];
        let mut scratch = Scratch::new(&layout);
        linearize(
            problem.factors(),
            &problem.values,
            &layout,
            &mut scratch,
            &mut h,
            &mut b,
        )
        .unwrap();
        let mut dense = DMatrix::zeros(n, n);
        let sym = layout.pattern.symbolic();
        for c in 0..n {
            let range = sym.col_range(c);
            for (i, &r) in sym.row_idx()[range.clone()].iter().enumerate() {
                dense[(r, c)] = h[range.start + i];
                dense[(c, r)] = h[range.start + i];
            }
        }
        (dense.try_inverse().unwrap(), layout)
    }

    #[test]
    fn joint_covariance_equals_the_dense_inverse() {
        let problem = square();
        let (inverse, layout) = dense_inverse(&problem);
        let marginals = Marginals::new(&problem).unwrap();
        let keys = [3, 1];
        let cov = marginals.covariance(&keys).unwrap();
        let row = |k: Key| layout.pattern.offset[layout.position_of_var[k as usize].unwrap()];
        for (a, &ka) in keys.iter().enumerate() {
            for (b, &kb) in keys.iter().enumerate() {
                let block = cov.block(a, b);
                for i in 0..3 {
                    for j in 0..3 {
                        let want = inverse[(row(ka) + i, row(kb) + j)];
                        let got = block[i * 3 + j];
                        assert!(
                            (got - want).abs() <= 1e-12 * want.abs().max(1e-6),
                            "{ka},{kb} ({i},{j}): {got} vs {want}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn anchored_variables_have_zero_covariance_and_bad_keys_are_named() {
        let mut problem = square();
        problem.retain_factors(|i| i < 4); // no prior: pose 0 becomes the gauge anchor
        let marginals = Marginals::new(&problem).unwrap();
        assert_eq!(marginals.gauge_fixed, vec![0]);
        let cov = marginals.covariance(&[0, 2]).unwrap();
        assert!(cov.block(0, 0).iter().all(|&x| x == 0.0));
        assert!(cov.block(1, 1)[0] > 0.0);
        assert_eq!(
            marginals.covariance(&[9]),
            Err(MarginalsError::UnknownVariable { key: 9 })
        );
        assert_eq!(
            marginals.covariance(&[2, 2]),
            Err(MarginalsError::Repeated { key: 2 })
        );
    }
}
