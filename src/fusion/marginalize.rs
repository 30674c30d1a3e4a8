//! Marginalisation: remove a variable from the problem and keep what its factors said about
//! the rest as a linear prior.
//!
//! The factors touching variable m are linearised at the current values (robust kernels
//! included), giving H and b over m and its free neighbours r. The Schur complement
//!
//! ```text
//! H* = H_rr − H_rm H_mm⁻¹ H_mr,    b* = b_r − H_rm H_mm⁻¹ b_m
//! ```
//!
//! is the information those factors carry about r once m is integrated out. With its
//! eigen-decomposition H* = V S Vᵀ, keeping eigenvalues above [`EIGEN_FLOOR`] (directions the
//! factors did not observe carry no information and must not become a prior), the
//! [`MarginalPrior`] gets `J = S^½ Vᵀ` and `r₀ = −S^−½ Vᵀ b*`, so that `JᵀJ = H*` and
//! `−Jᵀ r₀ = b*` (the course's and VINS-Mono's construction). The factors touching m are then
//! removed and m is held fixed (it keeps its last value, for the record).

use nalgebra::{DMatrix, DVector};

use crate::factors::MarginalPrior;
use crate::problem::{Key, Problem, ProblemError};
use crate::solver::linearize::{linearize, Scratch, SystemLayout};

/// Eigenvalues of H* at or below this are treated as unobserved directions and dropped.
pub const EIGEN_FLOOR: f64 = 1e-8;

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MarginalizeError {
    #[error("unknown variable {key}")]
    UnknownVariable { key: Key },
    #[error("variable {key} is already fixed or marginalised")]
    AlreadyFixed { key: Key },
    #[error("cannot evaluate the factors of variable {key}: {reason}")]
    Evaluation { key: Key, reason: String },
    #[error(
        "variable {key}: {kind} variables have no inverse retraction, so no prior can hold them"
    )]
    NoLocalCoordinates { key: Key, kind: &'static str },
    #[error(transparent)]
    Problem(#[from] ProblemError),
}

/// Marginalises `key` out of `problem`; returns the index of the prior factor it added (`None`
/// when no free variable shared a factor with it).
pub fn marginalize(problem: &mut Problem, key: Key) -> Result<Option<usize>, MarginalizeError> {
    let m = problem
        .values
        .index_of(key)
        .ok_or(MarginalizeError::UnknownVariable { key })?;
    if problem.values.is_fixed(m) {
        return Err(MarginalizeError::AlreadyFixed { key });
    }
    let touching: Vec<usize> = (0..problem.factors().len())
        .filter(|&f| problem.factors()[f].variables().contains(&m))
        .collect();
    let mut neighbours: Vec<usize> = touching
        .iter()
        .flat_map(|&f| problem.factors()[f].variables().iter().copied())
        .filter(|&v| v != m && !problem.values.is_fixed(v))
        .collect();
    neighbours.sort_unstable();
    neighbours.dedup();
    for &v in &neighbours {
        let variable = problem.values.variable(v);
        let mut probe = vec![0.0; variable.tangent_dim()];
        if !variable.local(variable, &mut probe) {
            return Err(MarginalizeError::NoLocalCoordinates {
                key: problem.values.key(v),
                kind: variable.kind(),
            });
        }
    }
    let prior = if neighbours.is_empty() {
        None
    } else {
        Some(schur_prior(problem, m, &neighbours, &touching, key)?)
    };
    problem.retain_factors(|f| !touching.contains(&f));
    problem.set_fixed(key, true)?;
    match prior {
        Some(prior) => {
            let rows = prior.residual.len();
            let index = problem.add_factor(
                Box::new(prior),
                &DMatrix::identity(rows, rows),
                None,
                format!("marginalisation of {key}"),
            )?;
            Ok(Some(index))
        }
        None => Ok(None),
    }
}

/// The prior on `neighbours` from the Schur complement of `m` in the factors `touching`.
fn schur_prior(
    problem: &Problem,
    m: usize,
    neighbours: &[usize],
    touching: &[usize],
    key: Key,
) -> Result<MarginalPrior, MarginalizeError> {
    let values = &problem.values;
    let subset: Vec<_> = touching.iter().map(|&f| &problem.factors()[f]).collect();
    let fixed: Vec<bool> = (0..values.len())
        .map(|v| v != m && !neighbours.contains(&v))
        .collect();
    let layout = SystemLayout::new(&subset, values, &fixed);
    let pattern = &layout.pattern;
    let mut scratch = Scratch::new(&layout);
    let mut h = vec![0.0; pattern.nnz()];
    let mut b = vec![0.0; layout.n()];
    linearize(&subset, values, &layout, &mut scratch, &mut h, &mut b).map_err(|e| {
        MarginalizeError::Evaluation {
            key,
            reason: e.to_string(),
        }
    })?;
    // Dense H and b in the order [m, neighbours…].
    let order: Vec<usize> = std::iter::once(m)
        .chain(neighbours.iter().copied())
        .collect();
    let mut start = vec![0; values.len()];
    let mut n = 0;
    for &v in &order {
        start[v] = n;
        n += values.variable(v).tangent_dim();
    }
    let dense_row = |row: usize| {
        let p = pattern.block_of_row(row);
        start[layout.var_at[p]] + row - pattern.offset[p]
    };
    let mut full = DMatrix::zeros(n, n);
    let mut rhs = DVector::zeros(n);
    for (c, &b_c) in b.iter().enumerate().take(pattern.n) {
        let dc = dense_row(c);
        rhs[dc] = b_c;
        let column = pattern.col_ptr[c]..pattern.col_ptr[c + 1];
        for (&r, &h_rc) in pattern.row_idx[column.clone()].iter().zip(&h[column]) {
            let dr = dense_row(r);
            full[(dr, dc)] = h_rc;
            full[(dc, dr)] = h_rc;
        }
    }
    let dm = values.variable(m).tangent_dim();
    let h_mm = full.view((0, 0), (dm, dm)).into_owned();
    let h_rm = full.view((dm, 0), (n - dm, dm)).into_owned();
    let h_rr = full.view((dm, dm), (n - dm, n - dm)).into_owned();
    let h_mm_inv = pseudo_inverse(&h_mm);
    let h_star = &h_rr - &h_rm * &h_mm_inv * h_rm.transpose();
    let b_star = rhs.rows(dm, n - dm) - &h_rm * &h_mm_inv * rhs.rows(0, dm);
    let h_star = (&h_star + h_star.transpose()) * 0.5;
    let eigen = h_star.symmetric_eigen();
    let kept: Vec<usize> = (0..eigen.eigenvalues.len())
        .filter(|&i| eigen.eigenvalues[i] > EIGEN_FLOOR)
        .collect();
    let mut jacobian = DMatrix::zeros(kept.len(), n - dm);
    let mut residual = DVector::zeros(kept.len());
    for (row, &i) in kept.iter().enumerate() {
        let s = eigen.eigenvalues[i];
        let v = eigen.eigenvectors.column(i);
        jacobian.row_mut(row).copy_from(&(v.transpose() * s.sqrt()));
        residual[row] = -v.dot(&b_star) / s.sqrt();
    }
    Ok(MarginalPrior::new(
        neighbours.iter().map(|&v| values.key(v)).collect(),
        neighbours
            .iter()
            .map(|&v| values.variable(v).clone_box())
            .collect(),
        jacobian,
        residual,
    ))
}

/// Inverse of a symmetric positive semi-definite matrix on its observed subspace.
fn pseudo_inverse(a: &DMatrix<f64>) -> DMatrix<f64> {
    let eigen = a.clone().symmetric_eigen();
    let mut inverse = DMatrix::zeros(a.nrows(), a.ncols());
    for i in 0..eigen.eigenvalues.len() {
        let s = eigen.eigenvalues[i];
        if s > EIGEN_FLOOR {
            let v = eigen.eigenvectors.column(i);
            inverse += v * v.transpose() / s;
        }
    }
    inverse
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector3;

    use super::*;
    use crate::factors::testing::Rng;
    use crate::factors::{PosePriorNav, RelativePoseNav};
    use crate::geometry::{so3, NavState};
    use crate::solver::{optimize, SolverOptions};

    /// A chain of five states with relative poses and noisy pose priors on every state.
    fn chain(seed: u64) -> Problem {
        let mut rng = Rng::new(seed);
        let mut problem = Problem::new();
        let truth: Vec<NavState> = (0..5)
            .map(|i| {
                let mut s = rng.nav_state();
                s.position = Vector3::new(i as f64, 0.1 * i as f64, 0.0);
                s.rotation = so3::exp(&Vector3::new(0.0, 0.0, 0.2 * i as f64));
                s
            })
            .collect();
        for (i, t) in truth.iter().enumerate() {
            let mut guess = *t;
            guess.position += rng.vector3(0.1);
            problem.add_variable(i as Key, Box::new(guess)).unwrap();
            let noisy = t.position + rng.vector3(0.05);
            let prior =
                PosePriorNav::new(i as Key, noisy, t.rotation * so3::exp(&rng.vector3(0.01)));
            problem
                .add_factor(Box::new(prior), &DMatrix::identity(6, 6), None, "prior")
                .unwrap();
        }
        for i in 0..4 {
            let (a, b) = (truth[i], truth[i + 1]);
            let dp = a.rotation.inverse() * (b.position - a.position) + rng.vector3(0.02);
            let dr = a.rotation.inverse() * b.rotation * so3::exp(&rng.vector3(0.01));
            let f = RelativePoseNav::new(i as Key, i as Key + 1, dp, dr);
            problem
                .add_factor(
                    Box::new(f),
                    &(DMatrix::identity(6, 6) * 100.0),
                    None,
                    "odometry",
                )
                .unwrap();
        }
        problem
    }

    fn solve(problem: &mut Problem) {
        // LM: velocities and biases are unobserved here, damping keeps them put.
        let options = SolverOptions {
            function_tolerance: 1e-14,
            gradient_tolerance: 1e-12,
            ..SolverOptions::bundle_adjustment()
        };
        optimize(problem, &options, &mut |_| {
            std::ops::ControlFlow::Continue(())
        })
        .unwrap();
    }

    /// At the optimum, marginalising the oldest states leaves the others' optimum where it was.
    #[test]
    fn marginalizing_at_the_optimum_keeps_the_optimum() {
        let mut full = chain(5);
        solve(&mut full);
        let mut window = chain(5);
        solve(&mut window);
        for key in [0, 1] {
            let prior = marginalize(&mut window, key).unwrap().unwrap();
            assert_eq!(window.factors()[prior].factor.keys(), &[key + 1]);
            assert!(window
                .factors()
                .iter()
                .all(|f| !f.factor.keys().contains(&key)));
        }
        // Move the remaining states off the optimum, then re-solve the window.
        for key in 2..5 {
            let v = window.values.index_of(key).unwrap();
            let mut delta = [0.0; 15];
            delta[0] = 0.05;
            delta[4] = 0.02;
            window.values.variable_mut(v).retract(&delta);
        }
        solve(&mut window);
        for key in 2..5 {
            let a = full.values.get_as::<NavState>(key).unwrap();
            let b = window.values.get_as::<NavState>(key).unwrap();
            let d = b.local(a);
            // Only the pose is observed; velocity and biases stay where they were.
            assert!(d.rows(0, 6).amax() < 1e-6, "state {key}: {d}");
        }
        assert!(window.values.is_fixed(window.values.index_of(0).unwrap()));
    }

    #[test]
    fn errors_are_typed() {
        let mut problem = chain(1);
        assert_eq!(
            marginalize(&mut problem, 99),
            Err(MarginalizeError::UnknownVariable { key: 99 })
        );
        marginalize(&mut problem, 0).unwrap();
        assert_eq!(
            marginalize(&mut problem, 0),
            Err(MarginalizeError::AlreadyFixed { key: 0 })
        );
    }
}
