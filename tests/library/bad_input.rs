//! Bad input gives typed errors with file and line, never a panic; gauge freedom is handled.

use crate::common;

use std::any::Any;

use factord::factors::{EvaluationError, Factor};
use factord::geometry::Se2;
use factord::io;
use factord::problem::{Key, Problem, Variable};
use factord::solver::{optimize, SolverError, SolverOptions};

const INFO: &str = "100 0 0 100 0 1000";

fn load_error(name: &str, vertices: &str, edges: Option<&str>) -> String {
    let dir = common::temp_dir(name);
    let v = dir.join("v.g2o");
    std::fs::write(&v, vertices).unwrap();
    let e = edges.map(|text| {
        let p = dir.join("e.g2o");
        std::fs::write(&p, text).unwrap();
        p
    });
    match io::load(&v, e.as_deref()) {
        Ok(_) => panic!("{name}: expected an error"),
        Err(err) => err.to_string(),
    }
}

#[test]
fn malformed_files_are_reported_with_line_and_reason() {
    let two = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n";
    let cases = [
        (
            "truncated",
            format!("{two}EDGE_SE2 0 1 1 0\n"),
            ":3:",
            "expects 11 fields",
        ),
        (
            "nan",
            format!("{two}EDGE_SE2 0 1 NaN 0 0 {INFO}\n"),
            ":3:",
            "not finite",
        ),
        (
            "inf",
            "VERTEX_SE2 0 inf 0 0\n".to_string(),
            ":1:",
            "not finite",
        ),
        (
            "word",
            format!("{two}EDGE_SE2 0 1 abc 0 0 {INFO}\n"),
            ":3:",
            "not a number",
        ),
        (
            "unknown id",
            format!("{two}EDGE_SE2 0 7 1 0 0 {INFO}\n"),
            ":3:",
            "unknown variable 7",
        ),
        (
            "duplicate",
            format!("{two}VERTEX_SE2 1 2 0 0\n"),
            ":3:",
            "already exists",
        ),
        (
            "non-pd",
            format!("{two}EDGE_SE2 0 1 1 0 0 1 2 0 1 0 1\n"),
            ":3:",
            "not positive definite",
        ),
        (
            "negative id",
            "VERTEX_SE2 -1 0 0 0\n".to_string(),
            ":1:",
            "not a valid id",
        ),
        (
            "unknown tag",
            format!("{two}EDGE_FOO 0 1\n"),
            ":3:",
            "unsupported record",
        ),
        (
            "mixed",
            format!("{two}VERTEX_SE3:QUAT 5 0 0 0 0 0 0 1\n"),
            ":3:",
            "mixes 2D and 3D",
        ),
        (
            "bad quaternion",
            "VERTEX_SE3:QUAT 5 0 0 0 0 0 0 0\n".to_string(),
            ":1:",
            "quaternion",
        ),
        ("empty", String::new(), "", "no vertices"),
        (
            "comments only",
            "# nothing\n\n".to_string(),
            "",
            "no vertices",
        ),
    ];
    for (name, text, line, reason) in cases {
        let msg = load_error(name, &text, None);
        assert!(msg.contains(line) && msg.contains(reason), "{name}: {msg}");
    }
    // TORO / course pair: edge-file errors name the edge file and line, or the edge itself.
    let vertices = "VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\n";
    let pair_cases = [
        (
            "toro",
            "EDGE2 1 0 1 0 0 20 0 20\n",
            "e.g2o:1:",
            "expects 11",
        ),
        (
            "toro-pd",
            "EDGE2 1 0 1 0 0 20 0 20 0 0 0\n",
            "EDGE2 1 0",
            "not positive definite",
        ),
    ];
    for (name, edges, place, reason) in pair_cases {
        let msg = load_error(name, vertices, Some(edges));
        assert!(msg.contains(place) && msg.contains(reason), "{name}: {msg}");
    }
}

#[test]
fn a_graph_without_anchor_gets_its_first_pose_fixed_and_says_so() {
    let dir = common::temp_dir("gauge");
    let path = dir.join("g.g2o");
    std::fs::write(&path, common::synthetic_manhattan(60, 4)).unwrap();
    let mut graph = io::load(&path, None).unwrap();
    let before = *graph.problem.values.get_as::<Se2>(0).unwrap();
    let summary = optimize(&mut graph.problem, &SolverOptions::default(), &mut |_| {
        std::ops::ControlFlow::Continue(())
    })
    .unwrap();
    assert_eq!(summary.used.gauge_fixed, vec![0]);
    assert!(summary.report().contains("fixed variable(s) [0]"));
    assert_eq!(*graph.problem.values.get_as::<Se2>(0).unwrap(), before);
    assert!(summary.final_chi2 < summary.initial_chi2);
    // With FIX present nothing is fixed automatically.
    std::fs::write(&path, common::synthetic_manhattan(60, 4) + "FIX 5\n").unwrap();
    let mut graph = io::load(&path, None).unwrap();
    let summary = optimize(&mut graph.problem, &SolverOptions::default(), &mut |_| {
        std::ops::ControlFlow::Continue(())
    })
    .unwrap();
    assert!(summary.used.gauge_fixed.is_empty());
}

/// A factor that only constrains its first variable, although it touches two: the second one is
/// left without information, so the normal equations are singular there.
#[derive(Debug)]
struct IgnoresSecond([Key; 2]);

impl Factor for IgnoresSecond {
    fn name(&self) -> &'static str {
        "ignores_second"
    }
    fn keys(&self) -> &[Key] {
        &self.0
    }
    fn residual_dim(&self) -> usize {
        3
    }
    fn variable_kinds(&self) -> &[&'static str] {
        &["se2", "se2"]
    }
    fn evaluate(
        &self,
        v: &[&dyn Variable],
        e: &mut [f64],
        j: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        let x = v[0].as_any().downcast_ref::<Se2>().unwrap();
        e.copy_from_slice(&[x.x - 1.0, x.y, x.theta]);
        if let Some(j) = j {
            j.fill(0.0);
            for k in 0..3 {
                j[k * 6 + k] = 1.0;
            }
        }
        Ok(())
    }
    fn as_any(&self) -> &dyn Any {
        self
    }
}

#[test]
fn a_singular_system_is_a_typed_error_naming_the_variable() {
    let mut problem = Problem::new();
    problem
        .add_variable(10, Box::new(Se2::new(0.0, 0.0, 0.0)))
        .unwrap();
    problem
        .add_variable(42, Box::new(Se2::new(0.0, 0.0, 0.0)))
        .unwrap();
    let info = nalgebra::DMatrix::identity(3, 3);
    // A prior anchors 10 (so no gauge fixing happens); 42 is touched but never constrained.
    problem
        .add_factor(
            Box::new(factord::factors::PriorSe2::new(10, Se2::identity())),
            &info,
            None,
            "prior",
        )
        .unwrap();
    problem
        .add_factor(Box::new(IgnoresSecond([10, 42])), &info, None, "test")
        .unwrap();
    let options = SolverOptions {
        initialization: factord::solver::Initialization::None,
        ..Default::default()
    };
    match optimize(&mut problem, &options, &mut |_| {
        std::ops::ControlFlow::Continue(())
    }) {
        Err(SolverError::IndeterminateSystem { keys }) => assert_eq!(keys, vec![42]),
        other => panic!("expected IndeterminateSystem, got {other:?}"),
    }
    // The values were not touched by the failed solve.
    assert!(problem.values.get_as::<Se2>(42).unwrap().x == 0.0);
}

#[test]
fn problem_rejects_bad_factors_without_changing_what_it_holds() {
    let mut problem = Problem::new();
    problem.add_variable(0, Box::new(Se2::identity())).unwrap();
    problem.add_variable(1, Box::new(Se2::identity())).unwrap();
    let between = || {
        Box::new(factord::factors::BetweenSe2::new(
            0,
            1,
            Se2::new(1.0, 0.0, 0.0),
        ))
    };
    let id3 = nalgebra::DMatrix::identity(3, 3);
    assert!(problem
        .add_factor(between(), &nalgebra::DMatrix::identity(2, 2), None, "e")
        .is_err());
    assert!(problem
        .add_variable(2, Box::new(Se2::new(f64::NAN, 0.0, 0.0)))
        .is_err());
    let nan_measurement = Box::new(factord::factors::BetweenSe2::new(
        0,
        1,
        Se2::new(f64::INFINITY, 0.0, 0.0),
    ));
    assert!(problem
        .add_factor(nan_measurement, &id3, None, "e")
        .is_err());
    let repeated = Box::new(factord::factors::BetweenSe2::new(1, 1, Se2::identity()));
    assert!(problem.add_factor(repeated, &id3, None, "e").is_err());
    assert_eq!(problem.factors().len(), 0);
    assert_eq!(problem.values.len(), 2);
    problem.add_factor(between(), &id3, None, "e").unwrap();
    assert_eq!(problem.factors().len(), 1);
}
