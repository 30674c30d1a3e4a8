//! M3500 (Olson's Manhattan world, Carlone's version) for streaming tests: its first poses as
//! g2o text, its least-squares optimum computed in process, and an estimate's distance to it.

use factord::geometry::Se2;
use serde_json::Value;

/// M3500's first `poses` poses and the edges among them, as g2o text.
pub fn m3500(poses: u64) -> Option<String> {
    let path = super::data_file("2d/carlone/input_M3500_g2o.g2o")?;
    let text = std::fs::read_to_string(path).unwrap();
    let kept = |l: &&str| {
        let f: Vec<&str> = l.split_whitespace().collect();
        match f.first() {
            Some(&"VERTEX_SE2") => f[1].parse::<u64>().unwrap() < poses,
            Some(&"EDGE_SE2") => f[1..3].iter().all(|k| k.parse::<u64>().unwrap() < poses),
            _ => false,
        }
    };
    Some(text.lines().filter(kept).collect::<Vec<_>>().join("\n") + "\n")
}

/// The least-squares optimum of the clean file, in process: every pose by key.
pub fn clean_optimum(text: &str) -> (f64, Vec<Se2>) {
    let mut graph = factord::io::g2o::parse(&[(std::path::Path::new("clean.g2o"), text)]).unwrap();
    let options = factord::solver::SolverOptions {
        function_tolerance: 1e-12,
        ..Default::default()
    };
    factord::solver::optimize(&mut graph.problem, &options, &mut |_| {
        std::ops::ControlFlow::Continue(())
    })
    .unwrap();
    let poses = (0..graph.vertex_order.len() as u64)
        .map(|k| *graph.problem.values.get_as::<Se2>(k).unwrap())
        .collect();
    (graph.problem.chi2(), poses)
}

/// The largest position error of the estimate against `optimum`, in metres.
pub fn worst_error(estimate: &Value, optimum: &[Se2]) -> f64 {
    estimate["variables"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| {
            let k = v["key"].as_u64().unwrap() as usize;
            let x: Vec<f64> = serde_json::from_value(v["value"].clone()).unwrap();
            (x[0] - optimum[k].x).hypot(x[1] - optimum[k].y)
        })
        .fold(0.0, f64::max)
}
