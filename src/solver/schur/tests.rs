//! The Schur steps against a sparse Cholesky of the whole system, and the optimum every linear
//! solver reaches.

use nalgebra::{DMatrix, Vector2, Vector3};

use faer::sparse::linalg::SupernodalThreshold;

use super::{plan, SchurPlan, SchurSolver};
use crate::factors::testing::Rng;
use crate::factors::{BetweenSe2, PriorSe2, ReprojectionSnavely};
use crate::geometry::{Point3, Se2, SnavelyCamera};
use crate::problem::{Gauge, Key, Problem};
use crate::solver::cholesky::SparseCholesky;
use crate::solver::linearize::{linearize, Scratch, SystemLayout};
use crate::solver::options::LinearSolverChoice;
use crate::solver::structure::ScalarRows;

/// A small BA: cameras looking at a cloud of points, observations with pixel noise, every
/// point seen by 2–4 cameras; cameras and points then perturbed.
pub(super) fn synthetic_bundle_adjustment(cameras: usize, points: usize, seed: u64) -> Problem {
    let mut rng = Rng::new(seed);
    let mut problem = Problem::with_gauge(Gauge::Free).eliminating(&["point3"]);
    let mut truth = Vec::new();
    for i in 0..cameras {
        let p = [
            0.1 * rng.normal(),
            0.1 * rng.normal(),
            0.1 * rng.normal(),
            rng.normal(),
            rng.normal(),
            -20.0 + rng.normal(),
            500.0 + 10.0 * rng.normal(),
            1e-3 * rng.normal(),
            1e-5 * rng.normal(),
        ];
        let camera = SnavelyCamera::from_bal(&p);
        truth.push(camera);
        let mut noisy = p;
        for v in noisy.iter_mut().take(6) {
            *v += 0.01 * rng.normal();
        }
        problem
            .add_variable(i as Key, Box::new(SnavelyCamera::from_bal(&noisy)))
            .unwrap();
    }
    let unit = DMatrix::identity(2, 2);
    for j in 0..points {
        let x = Vector3::new(3.0 * rng.normal(), 3.0 * rng.normal(), 3.0 * rng.normal());
        let key = (cameras + j) as Key;
        let noisy = x + 0.05 * Vector3::new(rng.normal(), rng.normal(), rng.normal());
        problem.add_variable(key, Box::new(Point3(noisy))).unwrap();
        let seen = 2 + (rng.next_u64() % 3) as usize;
        let first = (rng.next_u64() as usize) % cameras;
        for k in 0..seen.min(cameras) {
            let i = (first + k) % cameras;
            let z = truth[i].project(&x) + Vector2::new(rng.normal(), rng.normal());
            let factor = ReprojectionSnavely::new(i as Key, key, z);
            problem
                .add_factor(Box::new(factor), &unit, None, "obs")
                .unwrap();
        }
    }
    problem
}

/// `problem`'s plan for `choice`, its layout in the plan's ordering, and `H`, `b` linearised there.
pub(super) fn linearized(
    problem: &Problem,
    choice: LinearSolverChoice,
) -> (SchurPlan, SystemLayout, Vec<f64>, Vec<f64>) {
    let fixed = vec![false; problem.values.len()];
    let plan = plan(
        problem.factors(),
        &problem.values,
        &fixed,
        &problem.eliminate,
        choice,
        || None,
    )
    .expect("something to eliminate");
    let layout = SystemLayout::with_ordering(
        problem.factors(),
        &problem.values,
        &fixed,
        &plan.ordering,
        ScalarRows::Listed,
    );
    let mut scratch = Scratch::new(&layout);
    let mut h = vec![0.0; layout.pattern.nnz()];
    let mut b = vec![0.0; layout.n()];
    linearize(
        problem.factors(),
        &problem.values,
        &layout,
        &mut scratch,
        &mut h,
        &mut b,
    )
    .unwrap();
    (plan, layout, h, b)
}

/// The damped step (H + diag(shift))⁻¹ b through `solver`, and through a sparse Cholesky of
/// the same system in the same layout.
fn steps(problem: &Problem, choice: LinearSolverChoice) -> (Vec<f64>, Vec<f64>, bool) {
    let (plan, layout, h, b) = linearized(problem, choice);
    let pattern = &layout.pattern;
    let shift: Vec<f64> = (0..pattern.n)
        .map(|c| 1e-3 * h[pattern.diagonal_index(c)].max(1e-6))
        .collect();
    let mut schur = SchurSolver::new(pattern, &plan).unwrap();
    schur.factorize(pattern, &h, Some(&shift)).unwrap();
    let mut x = b.clone();
    schur.solve_in_place(pattern, &h, &mut x);

    let mut damped = h.clone();
    for (c, s) in shift.iter().enumerate() {
        damped[pattern.diagonal_index(c)] += s;
    }
    let mut chol = SparseCholesky::analyze(pattern, SupernodalThreshold::FORCE_SUPERNODAL).unwrap();
    chol.factorize(pattern, &damped).unwrap();
    let mut reference = b;
    chol.solve_in_place(&mut reference);
    (x, reference, schur.is_dense())
}

pub(super) fn assert_close(x: &[f64], reference: &[f64]) {
    let scale = reference.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    for (a, b) in x.iter().zip(reference) {
        assert!((a - b).abs() <= 1e-8 * scale, "{a} vs {b} (scale {scale})");
    }
}

#[test]
fn dense_and_sparse_schur_steps_match_sparse_cholesky() {
    let problem = synthetic_bundle_adjustment(7, 80, 3);
    for (choice, dense) in [
        (LinearSolverChoice::DenseSchur, true),
        (LinearSolverChoice::SparseSchur, false),
        (LinearSolverChoice::Auto, true),
    ] {
        let (x, reference, was_dense) = steps(&problem, choice);
        assert_eq!(was_dense, dense, "{choice:?}");
        assert_close(&x, &reference);
    }
}

/// Nothing about the mechanism is specific to BA: eliminate poses of a 2D pose graph. The
/// chosen poses never share a factor (a chain: every other one), and the step is exact.
#[test]
fn eliminates_any_kind_keeping_v_block_diagonal() {
    let mut rng = Rng::new(9);
    let mut problem = Problem::new().eliminating(&["se2"]);
    let n = 30;
    for i in 0..n {
        let guess = Se2::new(i as f64 + 0.1 * rng.normal(), 0.1 * rng.normal(), 0.0);
        problem.add_variable(i, Box::new(guess)).unwrap();
    }
    let information = DMatrix::identity(3, 3);
    problem
        .add_factor(
            Box::new(PriorSe2::new(0, Se2::new(0.0, 0.0, 0.0))),
            &information,
            None,
            "prior",
        )
        .unwrap();
    for i in 0..n - 1 {
        let step = Se2::new(1.0, 0.05 * rng.normal(), 0.02 * rng.normal());
        let factor = BetweenSe2::new(i, i + 1, step);
        problem
            .add_factor(Box::new(factor), &information, None, "odometry")
            .unwrap();
    }
    let loop_closure = BetweenSe2::new(0, n - 1, Se2::new((n - 1) as f64, 0.0, 0.0));
    problem
        .add_factor(Box::new(loop_closure), &information, None, "loop")
        .unwrap();
    let fixed = vec![false; n as usize];
    let planned = plan(
        problem.factors(),
        &problem.values,
        &fixed,
        &problem.eliminate,
        LinearSolverChoice::SparseSchur,
        || None,
    )
    .unwrap();
    assert!(planned.eliminated >= 10 && planned.eliminated <= 15);
    let (x, reference, _) = steps(&problem, LinearSolverChoice::SparseSchur);
    assert_close(&x, &reference);
}

#[test]
fn every_linear_solver_reaches_the_same_optimum() {
    use crate::solver::{optimize, SolverOptions};
    let mut costs = Vec::new();
    for choice in [
        LinearSolverChoice::SparseCholesky,
        LinearSolverChoice::DenseSchur,
        LinearSolverChoice::SparseSchur,
        LinearSolverChoice::IterativeSchur,
    ] {
        let mut problem = synthetic_bundle_adjustment(6, 60, 11);
        let options = SolverOptions {
            linear_solver: choice,
            function_tolerance: 1e-12,
            ..SolverOptions::bundle_adjustment()
        };
        let summary = optimize(&mut problem, &options, &mut |_| {
            std::ops::ControlFlow::Continue(())
        })
        .unwrap();
        assert!(summary.converged, "{choice:?}: {:?}", summary.termination);
        assert_eq!(
            summary.used.schur.is_some(),
            choice != LinearSolverChoice::SparseCholesky
        );
        costs.push(summary.final_chi2);
    }
    for c in &costs {
        assert!((c - costs[0]).abs() <= 1e-6 * costs[0], "{costs:?}");
    }
}

#[test]
fn an_indefinite_point_block_is_reported_at_its_rows() {
    // A point nobody observes: its V block is zero.
    let mut problem = synthetic_bundle_adjustment(3, 5, 4);
    let key = 100;
    problem
        .add_variable(key, Box::new(Point3(Vector3::new(0.0, 0.0, 0.0))))
        .unwrap();
    let (planned, layout, h, _) = linearized(&problem, LinearSolverChoice::Auto);
    let mut schur = SchurSolver::new(&layout.pattern, &planned).unwrap();
    let error = schur.factorize(&layout.pattern, &h, None).unwrap_err();
    assert_eq!(layout.key_at_row(&problem.values, error.row), key);
}

/// Stops at its `stop_at`-th checkpoint (counting from 1) and has `left` time.
struct CountingBudget {
    checkpoints: std::cell::Cell<usize>,
    stop_at: usize,
    left: Option<std::time::Duration>,
}

impl crate::solver::Budget for CountingBudget {
    fn checkpoint(&self) -> std::ops::ControlFlow<()> {
        self.checkpoints.set(self.checkpoints.get() + 1);
        if self.checkpoints.get() >= self.stop_at {
            std::ops::ControlFlow::Break(())
        } else {
            std::ops::ControlFlow::Continue(())
        }
    }

    fn remaining(&self) -> Option<std::time::Duration> {
        self.left
    }
}

/// The elimination checks its budget every `ELIMINATED_PER_CHECK` points and once more before
/// S's factorisation; a budget without the time S's factorisation is predicted to take stops it
/// before the elimination; a budget that never stops gives the unbudgeted factorisation.
#[test]
fn the_budget_is_checked_during_the_elimination_and_before_the_reduced_factorisation() {
    use super::ELIMINATED_PER_CHECK;
    let points = 3 * ELIMINATED_PER_CHECK + 10;
    let problem = synthetic_bundle_adjustment(8, points, 5);
    let (planned, layout, h, b) = linearized(&problem, LinearSolverChoice::SparseSchur);
    let pattern = &layout.pattern;
    // BA's gauge is free: H needs LM's damping to be positive definite.
    let shift: Vec<f64> = (0..pattern.n)
        .map(|c| 1e-3 * h[pattern.diagonal_index(c)].max(1e-6))
        .collect();
    let mut schur = SchurSolver::new(pattern, &planned).unwrap();
    let budget = |stop_at, left| CountingBudget {
        checkpoints: std::cell::Cell::new(0),
        stop_at,
        left,
    };

    let stopping = budget(2, None);
    let flow = schur
        .factorize_within(pattern, &h, Some(&shift), &stopping)
        .unwrap();
    assert!(flow.is_break());
    assert_eq!(stopping.checkpoints.get(), 2, "stopped at the second check");

    let no_time = budget(usize::MAX, Some(std::time::Duration::ZERO));
    let flow = schur
        .factorize_within(pattern, &h, Some(&shift), &no_time)
        .unwrap();
    assert!(flow.is_break());
    assert_eq!(no_time.checkpoints.get(), 0, "refused before eliminating");

    let endless = budget(usize::MAX, None);
    let flow = schur
        .factorize_within(pattern, &h, Some(&shift), &endless)
        .unwrap();
    assert!(flow.is_continue());
    assert_eq!(endless.checkpoints.get(), points / ELIMINATED_PER_CHECK + 1);
    let mut x = b.clone();
    schur.solve_in_place(pattern, &h, &mut x);
    schur.factorize(pattern, &h, Some(&shift)).unwrap();
    let mut unbudgeted = b;
    schur.solve_in_place(pattern, &h, &mut unbudgeted);
    assert_eq!(x, unbudgeted, "the same arithmetic, bit for bit");
}

/// Two threads linearise and eliminate what one does: H and b to rounding, the damped step to
/// rounding, for the dense and the sparse reduced system; and the work really is split.
#[test]
fn two_threads_give_one_threads_system_and_step() {
    let problem = synthetic_bundle_adjustment(12, 2000, 31);
    for choice in [
        LinearSolverChoice::DenseSchur,
        LinearSolverChoice::SparseSchur,
    ] {
        let (plan, mut layout, h1, b1) = linearized(&problem, choice);
        assert_eq!(layout.use_threads(problem.factors(), 2), 2, "{choice:?}");
        let mut scratch = Scratch::new(&layout);
        let (mut h2, mut b2) = (vec![f64::NAN; h1.len()], vec![f64::NAN; b1.len()]);
        let (factors, values) = (problem.factors(), &problem.values);
        linearize(factors, values, &layout, &mut scratch, &mut h2, &mut b2).unwrap();
        assert_close(&h2, &h1);
        assert_close(&b2, &b1);

        let pattern = &layout.pattern;
        let shift: Vec<f64> = (0..pattern.n)
            .map(|c| 1e-3 * h1[pattern.diagonal_index(c)].max(1e-6))
            .collect();
        let mut steps = Vec::new();
        for threads in [1, 2] {
            let mut schur = SchurSolver::new(pattern, &plan).unwrap();
            assert_eq!(schur.use_threads(threads), threads);
            // Twice: the second factorisation must not see the first one's partial sums.
            for _ in 0..2 {
                schur.factorize(pattern, &h1, Some(&shift)).unwrap();
            }
            let mut x = b1.clone();
            schur.solve_in_place(pattern, &h1, &mut x);
            steps.push(x);
        }
        assert_close(&steps[1], &steps[0]);
        assert!(steps[0].iter().any(|v| *v != 0.0));
    }
}
