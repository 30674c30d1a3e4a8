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
//! `−Jᵀ r₀ = b*` (the course's and VINS-Mono's construction). When every Cholesky pivot of a
//! matrix is above the floor (with the IMU, every direction is observed) its Cholesky factor
//! does the same job at a fraction of an eigen-decomposition's cost: H_mm⁻¹ by two triangular
//! solves, and H* = L Lᵀ gives `J = Lᵀ`, `r₀ = −L⁻¹ b*` (again `JᵀJ = H*`, `−Jᵀ r₀ = b*`).
//! The factors touching m are then removed and m is held fixed (it keeps its last value, for
//! the record).

use nalgebra::{DMatrix, DVector};

use crate::factors::{MarginalPrior, SqrtInformation};
use crate::problem::{Key, Problem, ProblemError};

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
            // Already whitened: unit information.
            let index = problem.add_factor_sqrt(
                Box::new(prior),
                SqrtInformation::identity(rows),
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
    let (full, rhs) = dense_system(problem, m, neighbours, touching, key)?;
    let n = full.nrows();
    let dm = values.variable(m).tangent_dim();
    let h_mm = full.view((0, 0), (dm, dm)).into_owned();
    let h_rm = full.view((dm, 0), (n - dm, dm)).into_owned();
    let h_rr = full.view((dm, dm), (n - dm, n - dm)).into_owned();
    let b_m = rhs.rows(0, dm).into_owned();
    // H_mm⁻¹ [H_mr | b_m]: by Cholesky when H_mm is clearly positive definite (the IMU observes
    // every direction of a keyframe), else on its observed subspace.
    let (x, y) = match well_conditioned_cholesky(&h_mm) {
        Some(c) => (c.solve(&h_rm.transpose()), c.solve(&b_m)),
        None => {
            let inverse = pseudo_inverse(&h_mm);
            (&inverse * h_rm.transpose(), &inverse * &b_m)
        }
    };
    let h_star = &h_rr - &h_rm * x;
    let b_star = rhs.rows(dm, n - dm) - &h_rm * y;
    let h_star = (&h_star + h_star.transpose()) * 0.5;
    let (jacobian, residual) = match well_conditioned_cholesky(&h_star) {
        // H* = L Lᵀ: J = Lᵀ, r₀ = −L⁻¹ b* (JᵀJ = H*, −Jᵀr₀ = b*).
        Some(c) => {
            let l = c.l();
            let residual = -l
                .solve_lower_triangular(&b_star)
                .expect("a Cholesky factor has a nonzero diagonal");
            (l.transpose(), residual)
        }
        None => eigen_square_root(&h_star, &b_star),
    };
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

/// H and b = −Jᵀr of the factors `touching`, linearised at the current values (robust kernels
/// included), dense in the order [m, neighbours…].
fn dense_system(
    problem: &Problem,
    m: usize,
    neighbours: &[usize],
    touching: &[usize],
    key: Key,
) -> Result<(DMatrix<f64>, DVector<f64>), MarginalizeError> {
    let values = &problem.values;
    let mut start = Vec::with_capacity(neighbours.len() + 1);
    let mut n = 0;
    for v in std::iter::once(m).chain(neighbours.iter().copied()) {
        start.push((v, n));
        n += values.variable(v).tangent_dim();
    }
    let dense_start = |v: usize| start.iter().find(|&&(w, _)| w == v).map(|&(_, o)| o);
    let mut full = DMatrix::zeros(n, n);
    let mut rhs = DVector::zeros(n);
    for &f in touching {
        let entry = &problem.factors()[f];
        let vars = entry.variables();
        let refs: Vec<&dyn crate::problem::Variable> =
            vars.iter().map(|&v| values.variable(v)).collect();
        let dims: Vec<usize> = refs.iter().map(|v| v.tangent_dim()).collect();
        let (d, cols) = (entry.factor.residual_dim(), dims.iter().sum::<usize>());
        let (mut e, mut r) = (vec![0.0; d], vec![0.0; d]);
        let (mut jac, mut wj) = (vec![0.0; d * cols], vec![0.0; d * cols]);
        entry
            .factor
            .evaluate(&refs, &mut e, Some(&mut jac))
            .map_err(|e| MarginalizeError::Evaluation {
                key,
                reason: e.to_string(),
            })?;
        entry.sqrt_information.whiten_vector(&e, &mut r);
        entry.sqrt_information.whiten_jacobian(&jac, cols, &mut wj);
        if let Some(kernel) = &entry.robust {
            kernel.correct(&mut r, &mut wj, cols);
        }
        let wj = DMatrix::from_row_slice(d, cols, &wj);
        let gram = wj.transpose() * &wj;
        let gradient = wj.transpose() * DVector::from_vec(r);
        let mut ci = 0;
        for (li, &vi) in vars.iter().enumerate() {
            let di = dims[li];
            if let Some(oi) = dense_start(vi) {
                let mut block = rhs.rows_mut(oi, di);
                block -= gradient.rows(ci, di);
                let mut cj = 0;
                for (lj, &vj) in vars.iter().enumerate() {
                    let dj = dims[lj];
                    if let Some(oj) = dense_start(vj) {
                        let mut block = full.view_mut((oi, oj), (di, dj));
                        block += gram.view((ci, cj), (di, dj));
                    }
                    cj += dj;
                }
            }
            ci += di;
        }
    }
    Ok((full, rhs))
}

/// The Cholesky factorisation of a symmetric matrix whose pivots all exceed [`EIGEN_FLOOR`]
/// (no direction is close to unobserved), or `None`.
fn well_conditioned_cholesky(a: &DMatrix<f64>) -> Option<nalgebra::Cholesky<f64, nalgebra::Dyn>> {
    let c = a.clone().cholesky()?;
    let l = c.l_dirty();
    (0..a.nrows())
        .all(|i| l[(i, i)] * l[(i, i)] > EIGEN_FLOOR)
        .then_some(c)
}

/// `J = S^½ Vᵀ` and `r₀ = −S^−½ Vᵀ b*` over the eigenvalues of `h_star` above [`EIGEN_FLOOR`].
fn eigen_square_root(h_star: &DMatrix<f64>, b_star: &DVector<f64>) -> (DMatrix<f64>, DVector<f64>) {
    let eigen = h_star.clone().symmetric_eigen();
    let kept: Vec<usize> = (0..eigen.eigenvalues.len())
        .filter(|&i| eigen.eigenvalues[i] > EIGEN_FLOOR)
        .collect();
    let mut jacobian = DMatrix::zeros(kept.len(), h_star.ncols());
    let mut residual = DVector::zeros(kept.len());
    for (row, &i) in kept.iter().enumerate() {
        let s = eigen.eigenvalues[i];
        let v = eigen.eigenvectors.column(i);
        jacobian.row_mut(row).copy_from(&(v.transpose() * s.sqrt()));
        residual[row] = -v.dot(b_star) / s.sqrt();
    }
    (jacobian, residual)
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
