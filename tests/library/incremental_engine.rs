//! The incremental engine against a batch solve of the same factors: a Manhattan-world 2D pose
//! graph with loop closures streamed pose by pose (each pose with every edge whose later end
//! it is, its value predicted from odometry), then compared with `solver::optimize` on the
//! whole graph. Also checks that updates stay local: an odometry step refactors a handful of
//! columns, not the map.

use std::ops::ControlFlow;

use factord::factors::testing::Rng;
use factord::factors::BetweenSe2;
use factord::geometry::Se2;
use factord::problem::Problem;
use factord::solver::incremental::{IncrementalEngine, UpdateParams};
use factord::solver::{optimize, SolverOptions};
use nalgebra::DMatrix;

/// Poses on a grid walk (unit steps, random turns), edges: odometry and, whenever the robot is
/// back on a cell it visited, a loop closure to the earliest visit. Measurements are the true
/// relative poses with noise.
pub(crate) fn manhattan(poses: usize, seed: u64) -> (Vec<Se2>, Vec<(usize, usize, Se2)>) {
    let mut rng = Rng::new(seed);
    let mut truth = vec![Se2::new(0.0, 0.0, 0.0)];
    let mut visited = std::collections::HashMap::new();
    visited.insert((0i64, 0i64), 0usize);
    let mut edges = Vec::new();
    let (mut x, mut y, mut heading) = (0i64, 0i64, 0i64);
    for k in 1..poses {
        let r = rng.uniform();
        heading = (heading
            + if r < 0.15 {
                1
            } else if r < 0.3 {
                3
            } else {
                0
            })
            % 4;
        let (dx, dy) = [(1, 0), (0, 1), (-1, 0), (0, -1)][heading as usize];
        x += dx;
        y += dy;
        let theta = heading as f64 * std::f64::consts::FRAC_PI_2;
        truth.push(Se2::new(
            x as f64,
            y as f64,
            factord::geometry::wrap_angle(theta),
        ));
        let noisy = |rng: &mut Rng, a: &Se2, b: &Se2| {
            let z = a.inverse().compose(b);
            Se2::new(
                z.x + 0.02 * rng.normal(),
                z.y + 0.02 * rng.normal(),
                z.theta + 0.01 * rng.normal(),
            )
        };
        edges.push((k - 1, k, noisy(&mut rng, &truth[k - 1], &truth[k])));
        if let Some(&j) = visited.get(&(x, y)) {
            if j + 5 < k {
                edges.push((j, k, noisy(&mut rng, &truth[j], &truth[k])));
            }
        } else {
            visited.insert((x, y), k);
        }
    }
    (truth, edges)
}

pub(crate) fn information() -> DMatrix<f64> {
    DMatrix::from_diagonal(&nalgebra::DVector::from_vec(vec![2500.0, 2500.0, 10000.0]))
}

pub(crate) fn add_edge(problem: &mut Problem, (i, j, z): &(usize, usize, Se2)) {
    problem
        .add_factor(
            Box::new(BetweenSe2::new(*i as u64, *j as u64, *z)),
            &information(),
            None,
            format!("{i}-{j}"),
        )
        .unwrap();
}

fn batch_optimum(poses: usize, edges: &[(usize, usize, Se2)], truth: &[Se2]) -> f64 {
    let mut problem = Problem::new();
    for (k, t) in truth.iter().enumerate().take(poses) {
        problem.add_variable(k as u64, Box::new(*t)).unwrap();
    }
    problem.set_fixed(0, true).unwrap();
    for e in edges.iter().filter(|e| e.1 < poses) {
        add_edge(&mut problem, e);
    }
    let options = SolverOptions {
        function_tolerance: 1e-12,
        ..Default::default()
    };
    optimize(&mut problem, &options, &mut |_| ControlFlow::Continue(())).unwrap();
    problem.chi2()
}

/// Adds pose `k` (its value predicted from the odometry edge `k-1 → k` at the current estimate)
/// and every edge whose later end is `k`, then updates the engine.
fn stream_pose(
    problem: &mut Problem,
    engine: &mut IncrementalEngine,
    edges_to: &[&(usize, usize, Se2)],
    k: usize,
    params: &UpdateParams,
) -> factord::solver::incremental::UpdateReport {
    let previous = *problem.values.get_as::<Se2>((k - 1) as u64).unwrap();
    let odometry = edges_to.iter().find(|e| e.0 == k - 1).unwrap();
    problem
        .add_variable(k as u64, Box::new(previous.compose(&odometry.2)))
        .unwrap();
    for e in edges_to {
        add_edge(problem, e);
    }
    engine.update(problem, params).unwrap()
}

/// The edges by their later end: what `stream_pose` sends with each pose.
fn edges_by_later_end(
    poses: usize,
    edges: &[(usize, usize, Se2)],
) -> Vec<Vec<&(usize, usize, Se2)>> {
    let mut by_end: Vec<Vec<&(usize, usize, Se2)>> = vec![Vec::new(); poses];
    for e in edges {
        by_end[e.1].push(e);
    }
    by_end
}

#[test]
fn streamed_graph_reaches_the_batch_optimum() {
    let poses = 1500;
    let (truth, edges) = manhattan(poses, 7);
    let loops = edges.iter().filter(|e| e.1 != e.0 + 1).count();
    assert!(loops > 100, "the walk closes loops ({loops})");
    let mut problem = Problem::new();
    problem.add_variable(0, Box::new(truth[0])).unwrap();
    problem.set_fixed(0, true).unwrap();
    let (mut engine, _) = IncrementalEngine::new(&mut problem, &[true]).unwrap();
    let params = UpdateParams::default();
    let mut odometry_columns = Vec::new();
    let by_later_end = edges_by_later_end(poses, &edges);
    for k in 1..poses {
        let report = stream_pose(&mut problem, &mut engine, &by_later_end[k], k, &params);
        if by_later_end[k].len() == 1 && report.relinearized_variables == 0 {
            odometry_columns.push(report.refactored_columns);
        }
    }
    // Odometry-only updates refactor the new pose and the previous root, nothing more.
    odometry_columns.sort_unstable();
    let median = odometry_columns[odometry_columns.len() / 2];
    assert!(
        median <= 3,
        "odometry updates refactored a median of {median} columns"
    );

    let optimum = batch_optimum(poses, &edges, &truth);
    let streamed = problem.chi2();
    assert!(
        (streamed - optimum) / optimum < 1e-3,
        "streamed chi2 {streamed} vs batch {optimum}"
    );
    // Polishing (a tight relinearisation threshold) ends at the batch optimum.
    let polish = UpdateParams {
        relinearize_threshold: 1e-6,
        wildfire_threshold: 0.0,
        max_passes: 20,
        relinearize_scalars: usize::MAX,
        defer_from: usize::MAX,
    };
    let report = engine.update(&mut problem, &polish).unwrap();
    let polished = problem.chi2();
    assert!(
        (polished - optimum).abs() / optimum < 1e-6,
        "polished chi2 {polished} vs batch {optimum} ({report:?})"
    );
    assert!((report.model_chi2 - polished).abs() / polished < 1e-6);
}

/// A polish in steps (a budget of scalar columns per update, as an idle session runs it): each
/// step relinearises only the largest steps that fit, refactors far less than the map, and the
/// steps together end at the batch optimum, as one unbounded polish does.
#[test]
fn polish_in_bounded_steps_reaches_the_batch_optimum() {
    let poses = 1200;
    let (truth, edges) = manhattan(poses, 3);
    let mut problem = Problem::new();
    problem.add_variable(0, Box::new(truth[0])).unwrap();
    problem.set_fixed(0, true).unwrap();
    let (mut engine, _) = IncrementalEngine::new(&mut problem, &[true]).unwrap();
    // As sessions stream: a loose threshold, one pass, so drift below it accumulates.
    let stream = UpdateParams {
        relinearize_threshold: 0.05,
        wildfire_threshold: 1e-5,
        max_passes: 1,
        relinearize_scalars: usize::MAX,
        defer_from: usize::MAX,
    };
    let by_later_end = edges_by_later_end(poses, &edges);
    for k in 1..poses {
        stream_pose(&mut problem, &mut engine, &by_later_end[k], k, &stream);
    }
    let optimum = batch_optimum(poses, &edges, &truth);
    // 96 poses' columns (3 scalars each).
    let budget = 96 * 3;
    let step = UpdateParams {
        relinearize_threshold: 1e-6,
        wildfire_threshold: 0.0,
        max_passes: 1,
        relinearize_scalars: budget,
        defer_from: usize::MAX,
    };
    let mut reports = Vec::new();
    loop {
        let report = engine.update(&mut problem, &step).unwrap();
        let done = report.relinearized_variables == 0 && report.max_delta <= 1e-6;
        reports.push(report);
        if done || reports.len() == 500 {
            break;
        }
    }
    let first = &reports[0];
    let widest = reports.iter().map(|r| r.refactored_columns).max().unwrap();
    eprintln!(
        "{} steps; the first relinearised {} variables and refactored {} columns; widest {widest}",
        reports.len(),
        first.relinearized_variables,
        first.refactored_columns
    );
    assert!(
        reports.len() > 3,
        "a long stream leaves more to relinearise than one step takes ({} steps)",
        reports.len()
    );
    assert!(
        first.relinearized_variables < poses / 4,
        "the first step relinearised {} of {poses} variables",
        first.relinearized_variables
    );
    assert!(
        widest < poses / 2,
        "a step refactored {widest} of {poses} columns (budget {budget})"
    );
    let polished = problem.chi2();
    assert!(
        (polished - optimum).abs() / optimum < 1e-6,
        "after {} steps: chi2 {polished} vs batch {optimum}",
        reports.len()
    );
}

/// Prints how far the streamed estimate is from the batch optimum for a few thresholds (run
/// with `--ignored --nocapture` when tuning; the assertions above are what must hold).
#[test]
#[ignore]
fn threshold_sweep() {
    let poses: usize = std::env::var("SWEEP_POSES")
        .ok()
        .and_then(|p| p.parse().ok())
        .unwrap_or(3000);
    let (truth, edges) = manhattan(poses, 11);
    let optimum = batch_optimum(poses, &edges, &truth);
    for (relin, passes) in [(0.1, 1), (0.05, 2), (0.01, 2), (0.01, 4), (0.001, 4)] {
        let mut problem = Problem::new();
        problem.add_variable(0, Box::new(truth[0])).unwrap();
        problem.set_fixed(0, true).unwrap();
        let (mut engine, _) = IncrementalEngine::new(&mut problem, &[true]).unwrap();
        let params = UpdateParams {
            relinearize_threshold: relin,
            wildfire_threshold: 1e-7,
            max_passes: passes,
            relinearize_scalars: usize::MAX,
            defer_from: usize::MAX,
        };
        let by_later_end = edges_by_later_end(poses, &edges);
        let (mut columns, mut worst, start) = (0, 0.0f64, std::time::Instant::now());
        for k in 1..poses {
            let t = std::time::Instant::now();
            let report = stream_pose(&mut problem, &mut engine, &by_later_end[k], k, &params);
            worst = worst.max(t.elapsed().as_secs_f64());
            columns += report.refactored_columns;
        }
        let total = start.elapsed().as_secs_f64();
        let chi2 = problem.chi2();
        let mut fixed = vec![false; poses];
        fixed[0] = true;
        let kept = engine.update(&mut problem, &params).unwrap().factor_nnz;
        let fresh = IncrementalEngine::new(&mut problem, &fixed)
            .unwrap()
            .1
            .factor_nnz;
        eprintln!("factor nnz: kept {kept}, fresh AMD {fresh}");
        let report = engine
            .update(
                &mut problem,
                &UpdateParams {
                    relinearize_threshold: 1e-4,
                    wildfire_threshold: 0.0,
                    max_passes: 10,
                    relinearize_scalars: usize::MAX,
                    defer_from: usize::MAX,
                },
            )
            .unwrap();
        eprintln!(
            "relin {relin} passes {passes}: total {total:.3}s worst {:.1}ms columns {columns} gap {:.2e}; polish to 1e-4: gap {:.2e} passes {} columns {} max_delta {:.1e}",
            worst * 1e3,
            (chi2 - optimum) / optimum,
            (problem.chi2() - optimum) / optimum,
            report.passes,
            report.refactored_columns,
            report.max_delta
        );
    }
}

/// Once the factor's fill has doubled since it was last ordered whole, an update orders and
/// eliminates the whole factor again: the stream goes on to the same estimate, the factor
/// after each whole order is about as large as before it at most, and the updates after one
/// keep refactoring only their paths.
#[test]
fn a_factor_whose_fill_doubled_is_ordered_whole_again() {
    let poses = 3000;
    let (truth, edges) = manhattan(poses, 11);
    let by_later_end = edges_by_later_end(poses, &edges);
    let params = UpdateParams::default();
    let stream = |from: Option<usize>| {
        let mut problem = Problem::new();
        problem.add_variable(0, Box::new(truth[0])).unwrap();
        problem.set_fixed(0, true).unwrap();
        let (mut engine, _) = IncrementalEngine::new(&mut problem, &[true]).unwrap();
        if let Some(nnz) = from {
            engine.order_whole_from(nnz);
        }
        let mut reports = Vec::new();
        let mut previous_nnz = 0;
        for k in 1..poses {
            let report = stream_pose(&mut problem, &mut engine, &by_later_end[k], k, &params);
            reports.push((previous_nnz, report.clone()));
            previous_nnz = report.factor_nnz;
        }
        (problem.chi2(), reports)
    };
    let (plain_chi2, plain) = stream(None);
    assert!(
        plain.iter().all(|(_, r)| !r.whole_reorder),
        "below the default size nothing is ordered whole"
    );
    let (chi2, reports) = stream(Some(20_000));
    let whole: Vec<_> = reports.iter().filter(|(_, r)| r.whole_reorder).collect();
    assert!(
        whole.len() >= 2,
        "the fill doubled more than once: {} whole orders",
        whole.len()
    );
    for (before, r) in &whole {
        // Summed over passes: a later pass may refactor some again.
        assert!(
            r.refactored_columns >= r.columns,
            "every column eliminated again: {} of {}",
            r.refactored_columns,
            r.columns
        );
        // AMD's order is a heuristic: a fresh one is not always smaller than the order the
        // updates kept (here within a few percent either way), but it bounds the fill.
        assert!(
            r.factor_nnz * 4 <= before * 5,
            "a whole order grew the factor: {before} → {}",
            r.factor_nnz
        );
    }
    // Odometry-only updates after the last whole order still refactor a column or two.
    let last = reports.iter().rposition(|(_, r)| r.whole_reorder).unwrap();
    let mut after: Vec<usize> = reports[last + 1..]
        .iter()
        .filter(|(_, r)| r.new_factors == 1 && r.relinearized_variables == 0)
        .map(|(_, r)| r.refactored_columns + r.updated_columns)
        .collect();
    after.sort_unstable();
    assert!(
        !after.is_empty() && after[after.len() / 2] <= 3,
        "{after:?}"
    );
    assert!(
        (chi2 - plain_chi2).abs() / plain_chi2 < 1e-3,
        "ordered whole {chi2} vs not {plain_chi2}"
    );
    let optimum = batch_optimum(poses, &edges, &truth);
    assert!((chi2 - optimum) / optimum < 1e-3, "{chi2} vs {optimum}");
}

/// An update that brings many poses at once (a session whose exact solve fell behind takes in
/// everything that arrived meanwhile) orders most of its variables with the rest of the part
/// it refactors, and only the newest last: moved last all together, the poses and the old ends
/// of their loop closures filled in as one dense root clique on the 300 000-pose city (see
/// `MAX_LAST` in the engine), and the newest pose sat a path of 24 columns below the root here.
/// The fill stays that of a fresh order, and odometry from the newest pose refactors a few
/// columns.
#[test]
fn an_update_of_many_poses_keeps_only_the_newest_last() {
    let (streamed, at_once) = (2000, 1000);
    let poses = streamed + at_once;
    let (truth, edges) = manhattan(poses, 5);
    let by_later_end = edges_by_later_end(poses, &edges);
    let params = UpdateParams::default();
    let mut problem = Problem::new();
    problem.add_variable(0, Box::new(truth[0])).unwrap();
    problem.set_fixed(0, true).unwrap();
    let (mut engine, _) = IncrementalEngine::new(&mut problem, &[true]).unwrap();
    for k in 1..streamed {
        stream_pose(&mut problem, &mut engine, &by_later_end[k], k, &params);
    }
    // The next thousand poses in one update, each predicted by odometry.
    for k in streamed..poses {
        let previous = *problem.values.get_as::<Se2>((k - 1) as u64).unwrap();
        let odometry = by_later_end[k].iter().find(|e| e.0 == k - 1).unwrap();
        problem
            .add_variable(k as u64, Box::new(previous.compose(&odometry.2)))
            .unwrap();
    }
    let closures = (streamed..poses)
        .flat_map(|k| &by_later_end[k])
        .filter(|e| e.1 != e.0 + 1)
        .count();
    assert!(closures > 50, "the update closes loops ({closures})");
    for e in (streamed..poses).flat_map(|k| &by_later_end[k]) {
        add_edge(&mut problem, e);
    }
    // One pass: a relinearisation pass after it would order the part again freely.
    let one_pass = UpdateParams {
        max_passes: 1,
        ..params.clone()
    };
    // Ordered whole, as an update is once the factor's fill has doubled.
    engine.order_whole_from(1);
    let report = engine.update(&mut problem, &one_pass).unwrap();
    assert!(report.whole_reorder);

    // A fresh engine over the same factors: one batch order of the whole graph.
    let mut fresh_problem = Problem::new();
    for k in 0..poses {
        let value = *problem.values.get_as::<Se2>(k as u64).unwrap();
        fresh_problem
            .add_variable(k as u64, Box::new(value))
            .unwrap();
    }
    fresh_problem.set_fixed(0, true).unwrap();
    for e in &edges {
        add_edge(&mut fresh_problem, e);
    }
    let mut fixed = vec![false; poses];
    fixed[0] = true;
    let (_, fresh) = IncrementalEngine::new(&mut fresh_problem, &fixed).unwrap();
    assert!(
        report.factor_nnz <= 2 * fresh.factor_nnz,
        "the update's fill {} against a fresh order's {}",
        report.factor_nnz,
        fresh.factor_nnz
    );
    // The newest pose stays at the root: odometry from it (nothing relinearised: the one pass
    // left large steps) refactors a column or two.
    let structure_only = UpdateParams {
        relinearize_threshold: f64::INFINITY,
        ..params.clone()
    };
    let step = (
        poses - 1,
        poses,
        truth[poses - 2].between(&truth[poses - 1]),
    );
    let next = stream_pose(&mut problem, &mut engine, &[&step], poses, &structure_only);
    assert!(
        next.refactored_columns + next.updated_columns <= 9,
        "odometry after the update: {next:?}"
    );
}
