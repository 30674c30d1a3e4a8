//! Wrong loop closures added to a 2D g2o file (issue 54; the benchmarks' generators are
//! `benches/outliers/generate.py` and `benches/robots/split.py`), each with the information of a
//! genuine closure of the file:
//! - random: uniform pose pairs at least 2 apart, uniform measurements (±10 m, any heading);
//! - perceptual aliasing: groups of 5-20 closures between consecutive poses of two segments,
//!   all measured as if the second segment were moved by one rigid transform (5-20 m, up to a
//!   radian, about the map's origin): consistent with each other, not with the map.

use std::collections::BTreeSet;

use factord::factors::testing::Rng;
use factord::geometry::Se2;

/// The file with `fraction` × its loop closures added as wrong ones at its end, the loop
/// closures it had, and the line numbers of the wrong ones.
pub fn add_random_wrong_closures(
    text: &str,
    fraction: f64,
    seed: u64,
) -> (String, usize, BTreeSet<usize>) {
    let poses = text.lines().filter(|l| l.starts_with("VERTEX_SE2")).count();
    let closures = loop_closures(text);
    let mut rng = Rng::new(seed);
    let mut file = Appended::new(text);
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
        file.push(format!(
            "EDGE_SE2 {i} {j} {} {} {} {}\n",
            10.0 * rng.symmetric(),
            10.0 * rng.symmetric(),
            rng.angle(),
            info.join(" ")
        ));
    }
    (file.text, closures.len(), file.added)
}

/// The file with `fraction` × its loop closures added as wrong ones in groups of perceptual
/// aliasing, measured against `optimum` (the clean file's solved g2o text), the loop closures it
/// had, and the line numbers of the wrong ones.
pub fn add_aliasing_wrong_closures(
    text: &str,
    optimum: &str,
    fraction: f64,
    seed: u64,
) -> (String, usize, BTreeSet<usize>) {
    let poses: Vec<Se2> = optimum
        .lines()
        .filter(|l| l.starts_with("VERTEX_SE2"))
        .map(|l| {
            let f: Vec<f64> = l
                .split_whitespace()
                .skip(2)
                .map(|v| v.parse().unwrap())
                .collect();
            Se2::new(f[0], f[1], f[2])
        })
        .collect();
    let closures = loop_closures(text);
    let info: Vec<&str> = closures[0].split_whitespace().skip(6).collect();
    let target = (fraction * closures.len() as f64).round() as usize;
    let mut rng = Rng::new(seed);
    let mut file = Appended::new(text);
    while file.added.len() < target {
        let size = (5 + rng.below(16)).min(target - file.added.len());
        let (i0, j0) = (rng.below(poses.len() - size), rng.below(poses.len() - size));
        if i0.abs_diff(j0) < size + 2 {
            continue;
        }
        let (distance, direction) = (5.0 + 15.0 * rng.uniform(), rng.angle());
        let shift = Se2::new(
            distance * direction.cos(),
            distance * direction.sin(),
            rng.symmetric(),
        );
        for k in 0..size {
            let (i, j) = (i0 + k, j0 + k);
            let z = poses[i].inverse().compose(&shift.compose(&poses[j]));
            file.push(format!(
                "EDGE_SE2 {i} {j} {} {} {} {}\n",
                z.x,
                z.y,
                z.theta,
                info.join(" ")
            ));
        }
    }
    (file.text, closures.len(), file.added)
}

/// The file's loop-closure lines (edges between poses whose ids are not consecutive).
fn loop_closures(text: &str) -> Vec<&str> {
    text.lines()
        .filter(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            f.first() == Some(&"EDGE_SE2")
                && f[1].parse::<u64>().unwrap().abs_diff(f[2].parse().unwrap()) != 1
        })
        .collect()
}

/// A file's text with lines appended, and the numbers of the appended lines.
struct Appended {
    text: String,
    lines: usize,
    added: BTreeSet<usize>,
}

impl Appended {
    fn new(text: &str) -> Self {
        let mut text = text.to_string();
        if !text.ends_with('\n') {
            text.push('\n');
        }
        Self {
            lines: text.lines().count(),
            text,
            added: BTreeSet::new(),
        }
    }

    /// Appends `line` (ending in a newline) and records its number.
    fn push(&mut self, line: String) {
        self.text += &line;
        self.lines += 1;
        self.added.insert(self.lines);
    }
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
