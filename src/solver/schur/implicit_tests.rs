//! The implicit Schur complement against the explicit one: its product against S formed by
//! dense algebra from the same H, its step against a sparse Cholesky of the whole system.

use faer::sparse::linalg::SupernodalThreshold;
use nalgebra::{DMatrix, DVector};

use super::tests::{assert_close, linearized, synthetic_bundle_adjustment};
use super::ImplicitSchur;
use crate::solver::cholesky::SparseCholesky;
use crate::solver::options::LinearSolverChoice;
use crate::solver::structure::BlockPattern;

/// H (both triangles) as a dense matrix, plus diag(shift).
fn dense(pattern: &BlockPattern, h: &[f64], shift: &[f64]) -> DMatrix<f64> {
    let mut m = DMatrix::from_diagonal(&DVector::from_column_slice(shift));
    for b in 0..pattern.dim.len() {
        for &(a, pair) in pattern.column_blocks(b) {
            let diagonal = a == b;
            for q in 0..pattern.dim[b] {
                for r in if diagonal { q } else { 0 }..pattern.dim[a] {
                    let v = h[pattern.value_index(pair, diagonal, r, q)];
                    let (i, j) = (pattern.offset[a] + r, pattern.offset[b] + q);
                    m[(i, j)] += v;
                    if i != j {
                        m[(j, i)] += v;
                    }
                }
            }
        }
    }
    m
}

fn shift_of(pattern: &BlockPattern, h: &[f64]) -> Vec<f64> {
    (0..pattern.n)
        .map(|c| 1e-3 * h[pattern.diagonal_index(c)].max(1e-6))
        .collect()
}

#[test]
fn the_implicit_product_is_the_explicit_schur_complement() {
    let problem = synthetic_bundle_adjustment(7, 80, 3);
    let (plan, layout, h, _) = linearized(&problem, LinearSolverChoice::IterativeSchur);
    assert!(plan.implicit);
    let pattern = &layout.pattern;
    let shift = shift_of(pattern, &h);
    let mut implicit = ImplicitSchur::new(pattern, &plan);
    let factorized = implicit
        .factorize_within(pattern, &h, Some(&shift), &crate::solver::budget::Unlimited)
        .unwrap();
    assert!(factorized.is_continue());
    let full = dense(pattern, &h, &shift);
    let ne = pattern.offset[plan.eliminated];
    let n = pattern.n - ne;
    let v = full.view((0, 0), (ne, ne)).into_owned();
    let w = full.view((ne, 0), (n, ne)).into_owned();
    let u = full.view((ne, ne), (n, n)).into_owned();
    let s = &u - &w * v.try_inverse().expect("V is invertible") * w.transpose();
    for seed in 0..3 {
        let x = DVector::from_fn(n, |i, _| ((i * 7 + seed * 13) as f64 * 0.37).sin());
        let expected = &s * &x;
        let mut y = vec![0.0; n];
        implicit.product(pattern, &h, x.as_slice(), &mut y);
        let scale = expected.amax();
        let error = (DVector::from_vec(y) - &expected).amax();
        assert!(error <= 1e-10 * scale, "error {error}, scale {scale}");
    }
}

#[test]
fn the_implicit_step_solved_tightly_is_the_direct_step() {
    let problem = synthetic_bundle_adjustment(7, 80, 3);
    let (plan, layout, h, b) = linearized(&problem, LinearSolverChoice::IterativeSchur);
    let pattern = &layout.pattern;
    let shift = shift_of(pattern, &h);
    let mut implicit = ImplicitSchur::new(pattern, &plan);
    implicit.set_forcing_max(0.0);
    let factorized = implicit
        .factorize_within(pattern, &h, Some(&shift), &crate::solver::budget::Unlimited)
        .unwrap();
    assert!(factorized.is_continue());
    let mut x = b.clone();
    implicit.solve_in_place(pattern, &h, &mut x);
    assert!(implicit.stats().iterations > 1);

    let mut damped = h.clone();
    for (c, s) in shift.iter().enumerate() {
        damped[pattern.diagonal_index(c)] += s;
    }
    let mut chol = SparseCholesky::analyze(pattern, SupernodalThreshold::FORCE_SUPERNODAL).unwrap();
    chol.factorize(pattern, &damped).unwrap();
    let mut reference = b;
    chol.solve_in_place(&mut reference);
    // CG stops at a relative residual of 1e-10 (or after n iterations): the step agrees to
    // S's conditioning times that (measured 2e-8).
    let scale = reference.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    for (p, q) in x.iter().zip(&reference) {
        assert!((p - q).abs() <= 1e-6 * scale, "{p} vs {q} (scale {scale})");
    }
}

/// Two threads factorise, multiply and solve what one does, to rounding (the parts' sums are
/// added in another order), and the work really is split; a second factorisation does not see
/// the first one's partial sums.
#[test]
fn two_threads_give_one_threads_product_and_step() {
    let problem = synthetic_bundle_adjustment(12, 2000, 31);
    let (plan, layout, h, b) = linearized(&problem, LinearSolverChoice::IterativeSchur);
    let pattern = &layout.pattern;
    let shift = shift_of(pattern, &h);
    let mut results = Vec::new();
    for threads in [1, 2] {
        let mut implicit = ImplicitSchur::new(pattern, &plan);
        assert_eq!(implicit.use_threads(threads), threads);
        implicit.set_forcing_max(0.0);
        for _ in 0..2 {
            let factorized = implicit
                .factorize_within(pattern, &h, Some(&shift), &crate::solver::budget::Unlimited)
                .unwrap();
            assert!(factorized.is_continue());
        }
        let n = implicit.reduced_dim();
        let x: Vec<f64> = (0..n).map(|i| (i as f64 * 0.37).sin()).collect();
        let mut y = vec![0.0; n];
        let mut helpers = std::mem::take(&mut implicit.helpers);
        implicit.product_parts((pattern, &h), &x, &mut y, &mut helpers);
        implicit.helpers = helpers;
        let mut step = b.clone();
        implicit.solve_in_place(pattern, &h, &mut step);
        results.push((y, step, implicit.stats().iterations));
    }
    let (one, two) = (&results[0], &results[1]);
    assert_close(&two.0, &one.0);
    assert_close(&two.1, &one.1);
    assert!(one.1.iter().any(|v| *v != 0.0));
    let (a, b) = (one.2 as i64, two.2 as i64);
    assert!(
        (a - b).abs() <= 1,
        "CG iterations {a} (one thread) and {b} (two)"
    );
}
