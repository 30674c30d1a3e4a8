//! The gate a possibly wrong loop closure passes in a streaming session: the innovation's
//! Mahalanobis distance from the incremental engine (`IncrementalEngine::innovation`) against
//! what adding the closure really costs (the rise of the optimal chi2), and against a closure
//! that is wrong.

use std::ops::ControlFlow;

use factord::factors::{BetweenSe2, SqrtInformation};
use factord::geometry::Se2;
use factord::problem::Problem;
use factord::solver::chi_square::chi_square_quantile;
use factord::solver::incremental::IncrementalEngine;
use factord::solver::{optimize, SolverOptions};

use super::incremental_engine::{add_edge, information, manhattan};

fn tight() -> SolverOptions {
    SolverOptions {
        function_tolerance: 1e-14,
        ..Default::default()
    }
}

/// The graph's first `poses` poses and the edges among them, solved, with its engine.
fn solved(
    poses: usize,
    truth: &[Se2],
    edges: &[(usize, usize, Se2)],
) -> (Problem, IncrementalEngine) {
    let mut problem = Problem::new();
    for (k, t) in truth.iter().enumerate().take(poses) {
        problem.add_variable(k as u64, Box::new(*t)).unwrap();
    }
    problem.set_fixed(0, true).unwrap();
    for e in edges.iter().filter(|e| e.1 < poses) {
        add_edge(&mut problem, e);
    }
    optimize(&mut problem, &tight(), &mut |_| ControlFlow::Continue(())).unwrap();
    let fixed: Vec<bool> = (0..problem.values.len())
        .map(|v| problem.values.is_fixed(v))
        .collect();
    let (engine, _) = IncrementalEngine::new(&mut problem, &fixed).unwrap();
    (problem, engine)
}

/// `d²` of the closure `i → j` measured as `z` against the solved `problem` of `edges`, and the
/// rise of the optimal chi2 once the closure is in.
fn gate_and_rise(
    problem: &Problem,
    engine: &IncrementalEngine,
    edges: &[(usize, usize, Se2)],
    (i, j, z): (usize, usize, Se2),
) -> (f64, f64) {
    let entry = problem
        .detached_entry(
            std::sync::Arc::new(BetweenSe2::new(i as u64, j as u64, z)),
            SqrtInformation::from_information(&information()).unwrap(),
            None,
            "candidate".into(),
        )
        .unwrap();
    let d2 = engine.innovation(problem, &entry).unwrap().unwrap();
    let before = problem.chi2();
    let mut with = Problem::new();
    for k in 0..problem.values.len() {
        let value = problem.values.variable(k).clone_box();
        with.add_variable(k as u64, value).unwrap();
    }
    with.set_fixed(0, true).unwrap();
    for e in edges.iter().filter(|e| e.1 < problem.values.len()) {
        add_edge(&mut with, e);
    }
    add_edge(&mut with, &(i, j, z));
    optimize(&mut with, &tight(), &mut |_| ControlFlow::Continue(())).unwrap();
    (d2, with.chi2() - before)
}

#[test]
fn a_correct_closure_after_a_long_excursion_passes_and_costs_what_the_gate_says() {
    let poses = 800;
    let (truth, edges) = manhattan(poses, 11);
    // The closures of the last 200 poses are held out; the first of them that spans the most
    // odometry is the hardest one to judge from the estimate alone.
    let held: Vec<&(usize, usize, Se2)> = edges
        .iter()
        .filter(|e| e.1 >= poses - 200 && e.1 != e.0 + 1)
        .collect();
    assert!(!held.is_empty(), "the walk revisits cells");
    let odometry: Vec<(usize, usize, Se2)> = edges
        .iter()
        .filter(|e| e.1 < poses - 200 || e.1 == e.0 + 1)
        .copied()
        .collect();
    let (problem, engine) = solved(poses, &truth, &odometry);
    let quantile = chi_square_quantile(3, 1.0 - 1e-6);
    let &&(i, j, z) = held.iter().max_by_key(|e| e.1 - e.0).unwrap();
    let (d2, rise) = gate_and_rise(&problem, &engine, &odometry, (i, j, z));
    let est_i = problem.values.get_as::<Se2>(i as u64).unwrap();
    let est_j = problem.values.get_as::<Se2>(j as u64).unwrap();
    let predicted = est_i.inverse().compose(est_j);
    let naive = {
        let dx = predicted.x - z.x;
        let dy = predicted.y - z.y;
        let dt = factord::geometry::wrap_angle(predicted.theta - z.theta);
        2500.0 * (dx * dx + dy * dy) + 10000.0 * dt * dt
    };
    println!("closure {i}->{j}: d² {d2:.3}, rise of the optimum {rise:.3}, the estimate's error alone {naive:.1}, quantile {quantile:.1}");
    assert!(
        d2 < quantile,
        "a correct closure passes: d² {d2} ≥ {quantile}"
    );
    assert!(
        naive > quantile,
        "the estimate alone would have refused it: {naive}"
    );
    assert!(
        (d2 - rise).abs() <= 0.1 * rise + 1e-2,
        "d² {d2} is the rise {rise}"
    );
}

#[test]
fn a_wrong_closure_is_far_beyond_the_quantile() {
    let poses = 600;
    let (truth, edges) = manhattan(poses, 5);
    let (problem, engine) = solved(poses, &truth, &edges);
    let quantile = chi_square_quantile(3, 1.0 - 1e-6);
    // Pose 550 as seen from pose 20, shifted by 5 m and 0.5 rad: what place
    // recognition returns for a similar-looking place next door.
    let truth_z = truth[20].inverse().compose(&truth[550]);
    let wrong = Se2::new(truth_z.x + 4.0, truth_z.y - 3.0, truth_z.theta + 0.5);
    let (d2, rise) = gate_and_rise(&problem, &engine, &edges, (20, 550, wrong));
    println!("wrong closure: d² {d2:.1}, rise {rise:.1}, quantile {quantile:.1}");
    assert!(d2 > 10.0 * quantile, "d² {d2}");
    assert!(
        (d2 - rise).abs() <= 0.2 * rise,
        "d² {d2} against the rise {rise}"
    );
}
