//! The chi2 of a streamed estimate and the batch optimum of the same graph, both computed in
//! this process by factord's own reader and solver (chi2 = Σ eᵀΩe over the file's edges, no
//! prior, no ½; 3D edges in factord's convention, g2o's information with the half-angle
//! rotation error converted, as the stream sends them).

use std::collections::HashSet;
use std::ops::ControlFlow;
use std::path::Path;

use serde_json::{json, Value};

use factord::api::catalogue::variable_codec;
use factord::io::parse_text;
use factord::solver::{optimize, SolverOptions};

/// The lines of a g2o (or GTSAM landmark) text among the vertices `kept` (what a `--limit`
/// stream saw).
pub fn restrict(text: &str, kept: &HashSet<u64>) -> String {
    let id = |t: &str| t.parse::<u64>().expect("a vertex id");
    text.lines()
        .filter(|l| {
            let t: Vec<&str> = l.split_whitespace().collect();
            match t.first() {
                Some(tag) if tag.starts_with("VERTEX") => kept.contains(&id(t[1])),
                Some(tag) if tag.starts_with("EDGE") || *tag == "ODOMETRY" => {
                    kept.contains(&id(t[1])) && kept.contains(&id(t[2]))
                }
                // A sighting from a kept pose (its landmark came with that pose or before).
                Some(&"LANDMARK") => kept.contains(&id(t[1])),
                _ => false,
            }
        })
        .map(|l| format!("{l}\n"))
        .collect()
}

/// Tight enough that the reference is the optimum, not a tolerance away from it.
fn batch_options() -> SolverOptions {
    SolverOptions {
        function_tolerance: 1e-12,
        ..SolverOptions::default()
    }
}

fn solve(problem: &mut factord::problem::Problem) -> f64 {
    optimize(
        problem,
        &batch_options(),
        &mut |_| ControlFlow::Continue(()),
    )
    .expect("batch solve")
    .final_chi2
}

/// `estimate`: the server's `GET /estimate` answer. Returns the streamed estimate's chi2, the
/// batch optimum (the lower of a Gauss-Newton solve from the file's values and one from the
/// streamed estimate) and the relative gap between them.
pub fn compare(text: &str, path: &str, estimate: &Value) -> Value {
    let parse = || parse_text(text, Path::new(path), None).expect("the graph parses");
    let mut streamed = parse();
    let values = &mut streamed.problem.values;
    let mut assigned = 0;
    for v in estimate["variables"]
        .as_array()
        .expect("estimate variables")
    {
        let key = v["key"].as_u64().expect("key");
        let kind = v["kind"].as_str().expect("kind");
        let value: Vec<f64> = serde_json::from_value(v["value"].clone()).expect("value");
        let decoded = (variable_codec(kind).expect("known kind").decode)(&value)
            .unwrap_or_else(|e| panic!("variable {key}: {e}"));
        let idx = values.index_of(key).expect("the file has the streamed key");
        assert!(values.set(idx, decoded.as_ref()), "same kind");
        assigned += 1;
    }
    assert_eq!(assigned, values.len(), "the estimate covers every pose");
    let streamed_chi2 = streamed.problem.chi2();
    let from_streamed = solve(&mut streamed.problem);
    let from_file = solve(&mut parse().problem);
    let optimum = from_file.min(from_streamed);
    json!({
        "final_chi2": streamed_chi2,
        "batch_chi2": optimum,
        "batch_chi2_from_file_values": from_file,
        "batch_chi2_from_streamed_estimate": from_streamed,
        "chi2_gap": streamed_chi2 / optimum - 1.0,
    })
}
