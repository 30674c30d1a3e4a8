//! Random wrong loop closures added to a 2D g2o file (issue 54; the benchmark's generator is
//! `benches/outliers/generate.py`): uniform pose pairs at least 2 apart, uniform measurements
//! (±10 m, any heading), each with the information of a genuine closure of the file.

use std::collections::BTreeSet;

use factord::factors::testing::Rng;

/// The file with `fraction` × its loop closures added as wrong ones at its end, the loop
/// closures it had, and the line numbers of the wrong ones.
pub fn add_random_wrong_closures(
    text: &str,
    fraction: f64,
    seed: u64,
) -> (String, usize, BTreeSet<usize>) {
    let poses = text.lines().filter(|l| l.starts_with("VERTEX_SE2")).count();
    let closures: Vec<&str> = text
        .lines()
        .filter(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            f.first() == Some(&"EDGE_SE2")
                && f[1].parse::<u64>().unwrap().abs_diff(f[2].parse().unwrap()) != 1
        })
        .collect();
    let mut rng = Rng::new(seed);
    let mut out = text.to_string();
    if !out.ends_with('\n') {
        out.push('\n');
    }
    let mut line = out.lines().count();
    let mut wrong = BTreeSet::new();
    for _ in 0..(fraction * closures.len() as f64).round() as usize {
        let (i, j) = loop {
            let (i, j) = (rng.below(poses), rng.below(poses));
            if i.abs_diff(j) >= 2 {
                break (i.min(j), i.max(j));
            }
        };
        let info: Vec<&str> = closures[rng.below(closures.len())]
            .split_whitespace()
            .skip(6)
            .collect();
        out += &format!(
            "EDGE_SE2 {i} {j} {} {} {} {}\n",
            10.0 * rng.symmetric(),
            10.0 * rng.symmetric(),
            rng.angle(),
            info.join(" ")
        );
        line += 1;
        wrong.insert(line);
    }
    (out, closures.len(), wrong)
}

/// The line numbers named by labels like `EDGE_SE2 3 7 (request body:12)`.
pub fn label_lines(labels: &serde_json::Value) -> BTreeSet<usize> {
    labels
        .as_array()
        .expect("rejected_labels is an array")
        .iter()
        .map(|l| {
            let l = l.as_str().unwrap();
            l.rsplit(':')
                .next()
                .unwrap()
                .trim_end_matches(')')
                .parse()
                .unwrap()
        })
        .collect()
}
