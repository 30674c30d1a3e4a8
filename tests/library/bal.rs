//! BAL files: the reference datasets' initial costs, a write/read round trip, and bad input.

use crate::common;

use std::path::Path;

use factord::io::bal;

fn assert_relative(a: f64, b: f64, tol: f64, what: &str) {
    assert!((a - b).abs() <= tol * b.abs(), "{what}: {a} vs {b}");
}

#[test]
fn reference_problems_have_the_documented_initial_cost() {
    for (file, cameras, points, observations, cost) in [
        ("bal/problem-16-22106-pre.txt", 16, 22106, 83718, 4.185660e6),
        ("bal/problem-49-7776-pre.txt", 49, 7776, 31843, 850912.5),
    ] {
        let Some(path) = common::data_file(file) else {
            return;
        };
        let b = bal::load(&path).unwrap();
        assert_eq!((b.num_cameras, b.num_points), (cameras, points));
        assert_eq!(b.problem.factors().len(), observations);
        // ½Σ‖r‖², the convention Ceres prints (4.185660e+06 in its docs for problem-16).
        assert_relative(b.cost(), cost, 1e-6, file);
    }
}

#[test]
fn small_problems_load_and_round_trip() {
    for file in [
        "bal/gtsam/dubrovnik-3-7-pre.txt",
        "bal/gtsam/dubrovnik-1-1-pre.txt",
    ] {
        let Some(path) = common::data_file(file) else {
            return;
        };
        let b = bal::load(&path).unwrap();
        let text = bal::to_string(&b);
        let again = bal::parse(Path::new("round trip"), &text).unwrap();
        assert_eq!(again.problem.factors().len(), b.problem.factors().len());
        assert_relative(again.cost(), b.cost(), 1e-9, file);
    }
}

fn error_of(text: &str) -> String {
    bal::parse(Path::new("bad.txt"), text)
        .expect_err("rejected")
        .to_string()
}

#[test]
fn bad_bal_input_is_a_clear_error() {
    // 1 camera, 1 point, 1 observation: 3 + 4 + 9 + 3 numbers.
    let good = "1 1 1\n0 0 -10.5 3.25\n0.1\n0.2\n0.3\n1\n2\n3\n500\n0\n0\n1\n2\n-10\n";
    assert!(bal::parse(Path::new("good.txt"), good).is_ok());
    let truncated = &good[..good.len() - 4];
    assert!(
        error_of(truncated).contains("the file has"),
        "{}",
        error_of(truncated)
    );
    let extra = format!("{good}7\n");
    assert!(
        error_of(&extra).contains("counts in the header"),
        "{}",
        error_of(&extra)
    );
    let camera_out_of_range = good.replacen("0 0 -10.5", "1 0 -10.5", 1);
    let e = error_of(&camera_out_of_range);
    assert!(
        e.contains("bad.txt:2") && e.contains("camera") && e.contains("below 1"),
        "{e}"
    );
    let point_out_of_range = good.replacen("0 0 -10.5", "0 5 -10.5", 1);
    assert!(error_of(&point_out_of_range).contains("point"));
    let nan = good.replacen("500", "nan", 1);
    let e = error_of(&nan);
    assert!(
        e.contains("bad.txt:9") && e.contains("parameter 6") && e.contains("not finite"),
        "{e}"
    );
    let word = good.replacen("3.25", "three", 1);
    assert!(error_of(&word).contains("not a number"));
    let negative = good.replacen("1 1 1", "1 -1 1", 1);
    assert!(error_of(&negative).contains("number of points"));
    assert!(error_of("").contains("number of cameras"));
}

#[test]
fn levenberg_marquardt_reaches_the_ceres_optimum() {
    use factord::solver::{optimize, LinearSolverChoice, SolverOptions};
    // Ceres' optima (½Σ‖r‖²) from its docs / our Ceres 2.1 runs; each problem through the dense
    // and the sparse reduced camera system, and problem-16 also without a Schur complement.
    for (file, optimum, choices) in [
        (
            "bal/problem-16-22106-pre.txt",
            18033.90,
            &[
                LinearSolverChoice::Auto,
                LinearSolverChoice::SparseSchur,
                LinearSolverChoice::SparseCholesky,
            ][..],
        ),
        (
            "bal/problem-49-7776-pre.txt",
            13344.32,
            &[LinearSolverChoice::Auto, LinearSolverChoice::SparseSchur][..],
        ),
    ] {
        let Some(path) = common::data_file(file) else {
            return;
        };
        for &choice in choices {
            let mut b = bal::load(&path).unwrap();
            let options = SolverOptions {
                linear_solver: choice,
                ..SolverOptions::bundle_adjustment()
            };
            let summary = optimize(&mut b.problem, &options, &mut |_| {
                std::ops::ControlFlow::Continue(())
            })
            .unwrap();
            let what = format!("{file} with {choice:?}");
            // The gauge (a similarity) is left to the damping, as Ceres does: nothing is fixed.
            assert!(summary.used.gauge_fixed.is_empty());
            assert_relative(b.cost(), optimum, 1e-3, &what);
            assert_relative(summary.final_chi2 / 2.0, b.cost(), 1e-12, &what);
            let schur = summary.used.schur.as_ref();
            match choice {
                LinearSolverChoice::SparseCholesky => assert!(schur.is_none(), "{what}"),
                _ => {
                    let schur = schur.expect("points eliminated");
                    assert_eq!(schur.eliminated_variables, b.num_points, "{what}");
                    assert_eq!(schur.reduced_dimension, 9 * b.num_cameras, "{what}");
                    let dense = choice == LinearSolverChoice::Auto;
                    assert_eq!(
                        schur.reduced_factorization,
                        if dense { "dense" } else { "sparse" },
                        "{what}"
                    );
                }
            }
        }
    }
}

/// Two threads (linearisation, the trial cost, the Schur complement's elimination and
/// back-substitution) reach one thread's optimum to rounding, in as many iterations, and the
/// Summary says two were used.
#[test]
fn two_threads_reach_one_threads_optimum() {
    use factord::solver::{optimize, SolverOptions};
    let Some(path) = common::data_file("bal/problem-16-22106-pre.txt") else {
        return;
    };
    let mut solved = Vec::new();
    for threads in [1, 2] {
        let mut b = bal::load(&path).unwrap();
        let options = SolverOptions {
            threads,
            ..SolverOptions::bundle_adjustment()
        };
        let summary = optimize(&mut b.problem, &options, &mut |_| {
            std::ops::ControlFlow::Continue(())
        })
        .unwrap();
        assert_eq!(summary.used.threads, threads);
        solved.push((b.cost(), summary.iterations));
    }
    let ((one, one_iterations), (two, two_iterations)) = (solved[0], solved[1]);
    assert_relative(two, one, 1e-9, "two threads against one");
    assert_eq!(two_iterations, one_iterations);
    assert_relative(one, 18033.90, 1e-3, "Ceres' optimum");
}

/// The implicit Schur complement (conjugate gradients on S's products, S never formed) reaches
/// the explicit one's optimum on problem-16, and the Summary says which solved and why.
#[test]
fn implicit_schur_reaches_the_explicit_optimum() {
    use factord::solver::{optimize, LinearSolverChoice, SolverOptions};
    let Some(path) = common::data_file("bal/problem-16-22106-pre.txt") else {
        return;
    };
    let mut costs = Vec::new();
    for choice in [LinearSolverChoice::Auto, LinearSolverChoice::IterativeSchur] {
        let mut b = bal::load(&path).unwrap();
        let options = SolverOptions {
            linear_solver: choice,
            ..SolverOptions::bundle_adjustment()
        };
        let summary = optimize(&mut b.problem, &options, &mut |_| {
            std::ops::ControlFlow::Continue(())
        })
        .unwrap();
        assert!(summary.converged, "{choice:?}: {:?}", summary.termination);
        let schur = summary.used.schur.expect("points eliminated");
        if choice == LinearSolverChoice::IterativeSchur {
            assert_eq!(schur.reduced_factorization, "implicit");
            assert!(summary.used.linear_solver.contains("conjugate gradients"));
            assert!(schur
                .implicit_reason
                .is_some_and(|r| r.contains("requested")));
            assert!(schur.cg_iterations.is_some_and(|n| n >= summary.iterations));
        } else {
            // Problem-16's S (144 unknowns) fits: auto keeps it explicit.
            assert_eq!(schur.reduced_factorization, "dense");
            assert!(schur.cg_iterations.is_none());
        }
        costs.push(b.cost());
    }
    assert_relative(costs[1], costs[0], 1e-6, "implicit against explicit");
    assert_relative(costs[0], 18033.90, 1e-3, "Ceres' optimum");
}
