//! Acceptance on the public benchmark datasets, with the default solver options.

use crate::common;

use factord::io::{self, g2o::chi2_g2o_convention};
use factord::solver::{optimize, Method, SolverOptions, Summary};

fn solve(
    relative: &str,
    edges: Option<&str>,
    options: &SolverOptions,
) -> Option<(Summary, io::PoseGraph)> {
    let path = common::data_file(relative)?;
    let edges = match edges {
        Some(e) => Some(common::data_file(e)?),
        None => None,
    };
    let mut graph = io::load(&path, edges.as_deref()).expect("dataset loads");
    let summary = optimize(&mut graph.problem, options, &mut |_| {
        std::ops::ControlFlow::Continue(())
    })
    .expect("solve succeeds");
    Some((summary, graph))
}

fn assert_relative(actual: f64, expected: f64, tolerance: f64, what: &str) {
    let rel = (actual - expected).abs() / expected.abs();
    assert!(
        rel <= tolerance,
        "{what}: {actual} vs {expected} (relative {rel:.2e} > {tolerance:.0e})"
    );
}

#[test]
fn course_intel_reaches_seed_figure_in_at_most_six_iterations() {
    let Some((s, _)) = solve(
        "2d/ls_slam/intel-v.dat",
        Some("2d/ls_slam/intel-e.dat"),
        &SolverOptions::default(),
    ) else {
        return;
    };
    assert_relative(s.initial_chi2, 2.05092e6, 1e-5, "intel initial");
    assert_relative(s.final_chi2, 65.402048, 1e-6, "intel final");
    assert!(s.iterations <= 6, "{} iterations", s.iterations);
    assert_eq!(s.used.gauge_fixed, vec![0]);
}

#[test]
fn course_killian_and_test_quadrat() {
    if let Some((s, _)) = solve(
        "2d/ls_slam/killian-v.dat",
        Some("2d/ls_slam/killian-e.dat"),
        &SolverOptions::default(),
    ) {
        assert_relative(s.initial_chi2, 3.08592e8, 1e-5, "killian initial");
        assert_relative(s.final_chi2, 10344.665262, 1e-6, "killian final");
    }
    if let Some((s, _)) = solve(
        "2d/ls_slam/test_quadrat-v.dat",
        Some("2d/ls_slam/test_quadrat-e.dat"),
        &SolverOptions::default(),
    ) {
        assert_relative(s.final_chi2, 4.94e4, 2e-3, "test_quadrat final");
    }
}

/// The 2D reference optima of shared/data/MANIFEST.md, to a relative 1e-6 with default options.
#[test]
fn every_2d_reference_optimum_with_the_default_method() {
    let cases = [
        ("2d/carlone/input_INTEL_g2o.g2o", 215.83023),
        ("2d/carlone/input_M3500_g2o.g2o", 137.91295),
        ("2d/misc/manhattanOlson3500.g2o", 146.07661),
        ("2d/sesync/intel.g2o", 45.004696),
        ("2d/converted/CSAIL_P.g2o", 38.956286),
        ("2d/converted/INTEL_P.g2o", 212.69691),
        ("2d/gtsam/noisyToyGraph.txt", 0.13665202),
    ];
    for (file, optimum) in cases {
        let Some((s, _)) = solve(file, None, &SolverOptions::default()) else {
            continue;
        };
        // The references are printed to 8 significant digits.
        assert_relative(s.final_chi2, optimum, 1e-6, file);
        assert!(s.converged, "{file}: {}", s.termination.message);
    }
}

#[test]
fn lm_and_dogleg_reach_the_same_optimum() {
    for method in [Method::LevenbergMarquardt, Method::Dogleg] {
        let options = SolverOptions {
            method,
            ..SolverOptions::default()
        };
        if let Some((s, _)) = solve("2d/carlone/input_M3500_g2o.g2o", None, &options) {
            assert_relative(s.final_chi2, 137.91295, 1e-6, method.name());
        }
    }
}

#[test]
fn sphere2500_reaches_g2o_optimum_in_g2o_convention() {
    let Some((s, g)) = solve("3d/sesync/sphere2500.g2o", None, &SolverOptions::default()) else {
        return;
    };
    let chi2 = chi2_g2o_convention(g.problem.factors(), &g.problem.values);
    assert_relative(chi2, 727.15, 1e-3, "sphere2500 (g2o convention)");
    assert!(s.converged);
}

#[test]
fn torus3d_converges_from_chordal_initialisation() {
    let Some((s, g)) = solve("3d/sesync/torus3D.g2o", None, &SolverOptions::default()) else {
        return;
    };
    assert!(s.converged, "{}", s.termination.message);
    assert_eq!(s.used.initialization, "chordal");
    let chi2 = chi2_g2o_convention(g.problem.factors(), &g.problem.values);
    assert!(chi2 < 1.5e4, "torus3D g2o chi2 {chi2}");
    assert!(s.iterations <= 10);
}
