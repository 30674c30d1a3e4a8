//! User-defined factors against built-in ones (issue 18, item 4): a pose graph solved twice from
//! the same start, once with the built-in `between_se2` and once with the same residual written
//! as an expression (`factord::factors::expression`), reporting the optimum both reach and the
//! solve time of each (median of `--rounds`, same process, same options), twice:
//! - `same_start`: both from the file's initial values (no chordal initialisation) to a tight
//!   function tolerance (1e-12), so both reach the optimum and the ratio is what evaluating the
//!   expression costs;
//! - `defaults`: the default options, where the built-in graph also gets the chordal start (an
//!   initialisation that needs to know a factor is a relative pose; a user-defined one is not
//!   known to be).
//!
//! A BAL file (`problem-*.txt`) is solved the same way with BAL's reprojection written as an
//! expression (`proto/v1/examples/factor-type-reprojection.example.json`), with the bundle
//! adjustment options (LM, points eliminated by the Schur complement).
//!
//! `cargo bench --bench expression -- <file.g2o | problem-*.txt> [--rounds 20]`

#[path = "../args.rs"]
mod args;
#[path = "../stats.rs"]
mod stats;

use std::time::Instant;

use factord::factors::expression::{ExpressionType, FactorTypeDefinition};
use std::sync::Arc;

use factord::factors::autodiff::{AutoBetweenSe2, AutoFactor};
use factord::factors::{BetweenSe2, Factor, ReprojectionSnavely};
use factord::geometry::Se2;
use factord::problem::Problem;
use factord::solver::{self, Initialization, SolverOptions};

/// The built-in residual `[R_ijᵀ (R_iᵀ (t_j − t_i) − t_ij); wrap(θ_j − θ_i − θ_ij)]`.
const BETWEEN_SE2: &str = r#"{
    "name": "user_between_se2",
    "variables": [{"name": "a", "kind": "se2"}, {"name": "b", "kind": "se2"}],
    "parameters": [{"name": "z", "kind": "se2"}],
    "residual": [
        {"translation": [{"between": ["z", {"between": ["a", "b"]}]}]},
        {"wrap": [{"angle": [{"between": ["z", {"between": ["a", "b"]}]}]}]}
    ]
}"#;

/// A copy of `original` (same gauge, same eliminated kinds) whose factors `make` rebuilds.
fn copy_with(original: &Problem, make: &dyn Fn(&dyn Factor) -> Box<dyn Factor>) -> Problem {
    let mut problem = Problem::with_gauge(original.gauge).eliminating(&original.eliminate);
    let values = &original.values;
    for idx in 0..values.len() {
        problem
            .add_variable(values.key(idx), values.variable(idx).clone_box())
            .expect("same variables");
        problem
            .set_fixed(values.key(idx), values.is_fixed(idx))
            .expect("just added");
    }
    for entry in original.factors() {
        problem
            .add_factor_sqrt(
                make(entry.factor.as_ref()),
                entry.sqrt_information.clone(),
                entry.robust,
                entry.label.clone(),
            )
            .expect("same factors");
    }
    problem
}

fn compile(json: &str) -> Arc<ExpressionType> {
    let definition: FactorTypeDefinition = serde_json::from_str(json).expect("valid JSON");
    ExpressionType::compile(definition).expect("the definition compiles")
}

/// Solves a fresh copy of `problem` `rounds` times; the median solve time and the last result.
fn solve(
    problem: &Problem,
    options: &SolverOptions,
    rounds: usize,
    copy: impl Fn(&Problem) -> Problem,
) -> (f64, Problem, usize) {
    let mut times = Vec::new();
    let mut last = None;
    let mut iterations = 0;
    for _ in 0..rounds {
        let mut p = copy(problem);
        let start = Instant::now();
        let summary =
            solver::optimize(
                &mut p,
                options,
                &mut |_| std::ops::ControlFlow::Continue(()),
            )
            .expect("the solve succeeds");
        times.push(start.elapsed().as_secs_f64());
        iterations = summary.iterations;
        last = Some(p);
    }
    (
        stats::median(&mut times),
        last.expect("at least one round"),
        iterations,
    )
}

fn main() {
    let args = args::Args::from_env();
    let file = args.first("usage: expression <file.g2o | BAL problem-*.txt> [--rounds N]");
    let rounds: usize = args.parsed("--rounds", 20);
    let bal = file.ends_with(".txt");
    let (original, ty, runs) = if bal {
        let problem = factord::io::bal::load(file.as_ref())
            .expect("a readable BAL file")
            .problem;
        let ty = compile(include_str!(
            "../../proto/v1/examples/factor-type-reprojection.example.json"
        ));
        (
            problem,
            ty,
            vec![("bundle_adjustment", SolverOptions::bundle_adjustment())],
        )
    } else {
        let problem = factord::io::load(file.as_ref(), None)
            .expect("a readable 2D g2o file")
            .problem;
        let same_start = SolverOptions {
            initialization: Initialization::None,
            function_tolerance: 1e-12,
            ..SolverOptions::default()
        };
        (
            problem,
            compile(BETWEEN_SE2),
            vec![
                ("same_start", same_start),
                ("defaults", SolverOptions::default()),
            ],
        )
    };
    let built_in = |f: &dyn Factor| -> Box<dyn Factor> {
        if let Some(b) = f.as_any().downcast_ref::<BetweenSe2>() {
            return Box::new(b.clone());
        }
        let r = f
            .as_any()
            .downcast_ref::<ReprojectionSnavely>()
            .expect("between_se2 or reprojection_snavely");
        Box::new(r.clone())
    };
    let expression = |f: &dyn Factor| -> Box<dyn Factor> {
        let measurement = match f.as_any().downcast_ref::<BetweenSe2>() {
            Some(b) => vec![b.measurement.x, b.measurement.y, b.measurement.theta],
            None => {
                let r = f
                    .as_any()
                    .downcast_ref::<ReprojectionSnavely>()
                    .expect("between_se2 or reprojection_snavely");
                vec![r.observed.x, r.observed.y]
            }
        };
        Box::new(
            ty.build(f.keys(), &measurement)
                .expect("a valid measurement"),
        )
    };
    let rust_autodiff = |f: &dyn Factor| -> Box<dyn Factor> {
        let b = f
            .as_any()
            .downcast_ref::<BetweenSe2>()
            .expect("between_se2");
        Box::new(
            AutoFactor::new(b.keys().to_vec(), AutoBetweenSe2(b.measurement)).expect("two se2"),
        )
    };
    let (operations, varying) = ty.operations();
    let mut report = serde_json::json!({"file": file, "rounds": rounds,
        "tape": {"operations": operations, "run_per_evaluation": varying}});
    for (name, options) in runs {
        let (t_built_in, solved_built_in, it_built_in) =
            solve(&original, &options, rounds, |p| copy_with(p, &built_in));
        let (t_expression, solved_expression, it_expression) =
            solve(&original, &options, rounds, |p| copy_with(p, &expression));
        // The same residual in Rust with automatic derivatives (factors::autodiff), 2D only.
        let rust = (!bal).then(|| {
            let (t, solved, iterations) = solve(&original, &options, rounds, |p| {
                copy_with(p, &rust_autodiff)
            });
            serde_json::json!({"solve_seconds": t, "chi2": solved.chi2(), "iterations": iterations,
                "time_ratio": t / t_built_in})
        });
        let (c0, c1) = (solved_built_in.chi2(), solved_expression.chi2());
        report[name] = serde_json::json!({
            "built_in": {"solve_seconds": t_built_in, "chi2": c0, "iterations": it_built_in},
            "expression": {"solve_seconds": t_expression, "chi2": c1, "iterations": it_expression},
            "time_ratio": t_expression / t_built_in,
            "chi2_relative_difference": (c1 - c0).abs() / c0,
            "max_pose_difference": (!bal).then(|| max_pose_difference(&solved_built_in, &solved_expression)),
            "rust_autodiff": rust,
        });
    }
    println!("{report}");
}

/// The largest difference of a coordinate (x, y or the wrapped angle) between two estimates.
fn max_pose_difference(a: &Problem, b: &Problem) -> f64 {
    let mut max_difference: f64 = 0.0;
    for idx in 0..a.values.len() {
        let key = a.values.key(idx);
        let p = a.values.get_as::<Se2>(key).expect("se2");
        let q = b.values.get_as::<Se2>(key).expect("same keys");
        let dtheta = factord::geometry::wrap_angle(p.theta - q.theta);
        max_difference = max_difference
            .max((p.x - q.x).abs())
            .max((p.y - q.y).abs())
            .max(dtheta.abs());
    }
    max_difference
}
