//! The graphs streamed: `input_M3500_g2o` read from the shared data, and a Manhattan-like 2D
//! pose graph of any size generated here (a random walk on a 1 m grid with odometry and loop
//! closures to earlier poses on the same cell, measured with noise). Both become JSON batches:
//! pose by pose (a robot's stream) or in chunks of exactly `n` factors (bulk ingest).

use std::collections::HashMap;
use std::path::PathBuf;

use serde_json::{json, Value};

/// A 2D pose graph: poses by key 0..n with their initial guess; edges (from, to, measurement,
/// information upper triangle) in the order a robot makes them (by their later end).
pub struct Graph {
    pub guesses: Vec<[f64; 3]>,
    pub edges: Vec<Edge>,
}

pub struct Edge {
    pub from: usize,
    pub to: usize,
    pub z: [f64; 3],
    pub info: [f64; 6],
}

/// The data directory (`FACTORD_DATA`, default `../shared/data` next to the checkout).
pub fn data_file(relative: &str) -> Result<PathBuf, String> {
    let dir = std::env::var_os("FACTORD_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data"));
    let path = dir.join(relative);
    if path.is_file() {
        Ok(path)
    } else {
        Err(format!("{} not found (set FACTORD_DATA)", path.display()))
    }
}

/// An SE2 g2o file (VERTEX_SE2 / EDGE_SE2 lines).
pub fn parse_g2o_se2(text: &str) -> Graph {
    let mut guesses: Vec<(usize, [f64; 3])> = Vec::new();
    let mut edges = Vec::new();
    for line in text.lines() {
        let t: Vec<&str> = line.split_whitespace().collect();
        let num = |i: usize| -> f64 { t[i].parse().expect("a number") };
        match t.first() {
            Some(&"VERTEX_SE2") => {
                guesses.push((t[1].parse().expect("key"), [num(2), num(3), num(4)]))
            }
            Some(&"EDGE_SE2") => edges.push(Edge {
                from: t[1].parse().expect("key"),
                to: t[2].parse().expect("key"),
                z: [num(3), num(4), num(5)],
                info: [num(6), num(7), num(8), num(9), num(10), num(11)],
            }),
            _ => {}
        }
    }
    guesses.sort_by_key(|g| g.0);
    assert!(
        guesses.iter().enumerate().all(|(i, g)| g.0 == i),
        "keys 0..n"
    );
    edges.sort_by_key(|e| e.from.max(e.to));
    Graph {
        guesses: guesses.into_iter().map(|g| g.1).collect(),
        edges,
    }
}

fn compose(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    let (s, c) = a[2].sin_cos();
    [
        a[0] + c * b[0] - s * b[1],
        a[1] + s * b[0] + c * b[1],
        wrap(a[2] + b[2]),
    ]
}

/// a⁻¹ b
fn between(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    let (s, c) = a[2].sin_cos();
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    [c * dx + s * dy, -s * dx + c * dy, wrap(b[2] - a[2])]
}

fn wrap(t: f64) -> f64 {
    (t + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI
}

/// The library's test generator (SplitMix64, Box–Muller normals).
pub use factord::factors::testing::Rng;

/// A Manhattan-like graph of `poses` poses: unit steps on a grid turning left/right with
/// probability 1/4 each, odometry with σ = 5 cm / 0.01 rad, and a loop closure to one earlier
/// pose on the same grid cell (at least 20 poses back, the most recent such) with probability
/// 1/2. Initial guesses from the odometry.
pub fn manhattan(poses: usize, seed: u64) -> Graph {
    let mut rng = Rng::new(seed);
    let (st, sr) = (0.05, 0.01);
    let info = [
        1.0 / (st * st),
        0.0,
        0.0,
        1.0 / (st * st),
        0.0,
        1.0 / (sr * sr),
    ];
    let mut truth = vec![[0.0, 0.0, 0.0]];
    let mut guesses = vec![[0.0, 0.0, 0.0]];
    let mut edges = Vec::new();
    let mut on_cell: HashMap<(i64, i64), Vec<usize>> = HashMap::new();
    on_cell.entry((0, 0)).or_default().push(0);
    let noisy = |rng: &mut Rng, z: [f64; 3]| {
        [
            z[0] + st * rng.normal(),
            z[1] + st * rng.normal(),
            wrap(z[2] + sr * rng.normal()),
        ]
    };
    for i in 1..poses {
        let turn = match rng.next_u64() % 4 {
            0 => std::f64::consts::FRAC_PI_2,
            1 => -std::f64::consts::FRAC_PI_2,
            _ => 0.0,
        };
        let t = compose(truth[i - 1], [1.0, 0.0, turn]);
        truth.push(t);
        let z = noisy(&mut rng, between(truth[i - 1], t));
        guesses.push(compose(guesses[i - 1], z));
        edges.push(Edge {
            from: i - 1,
            to: i,
            z,
            info,
        });
        let cell = (t[0].round() as i64, t[1].round() as i64);
        let earlier = on_cell.entry(cell).or_default();
        if let Some(&j) = earlier.iter().rev().find(|&&j| j + 20 <= i) {
            if rng.uniform() < 0.5 {
                let z = noisy(&mut rng, between(truth[j], t));
                edges.push(Edge {
                    from: j,
                    to: i,
                    z,
                    info,
                });
            }
        }
        earlier.push(i);
    }
    Graph { guesses, edges }
}

fn factor(e: &Edge) -> Value {
    json!({"type": "between_se2", "keys": [e.from, e.to], "measurement": e.z,
           "information": e.info})
}

/// Pose by pose, as a robot streams: batch k holds pose k and every edge whose later end is k;
/// a pose with odometry from k−1 has no value (the server predicts it); pose 0 is fixed.
/// Numbered by `producer` 1, 2, 3, …. Returns (serialised batch, factors in it).
pub fn per_pose(g: &Graph, producer: &str) -> Vec<(String, usize)> {
    let mut by_later: Vec<Vec<&Edge>> = (0..g.guesses.len()).map(|_| Vec::new()).collect();
    for e in &g.edges {
        by_later[e.from.max(e.to)].push(e);
    }
    by_later
        .iter()
        .enumerate()
        .map(|(k, edges)| {
            let odometry = edges.iter().any(|e| e.from + 1 == k && e.to == k);
            let variable = if k == 0 {
                json!({"key": 0, "kind": "se2", "value": g.guesses[0], "fixed": true})
            } else if odometry {
                json!({"key": k, "kind": "se2"})
            } else {
                json!({"key": k, "kind": "se2", "value": g.guesses[k]})
            };
            let factors: Vec<Value> = edges.iter().map(|e| factor(e)).collect();
            let body = json!({"producer": producer, "producer_seq": k + 1,
                              "variables": [variable], "factors": factors});
            (body.to_string(), edges.len())
        })
        .collect()
}

/// Chunks of exactly `size` factors (the last one may be smaller) in edge order; each chunk
/// declares (with its guess) every pose first referenced in it; pose 0 is fixed. Numbered by
/// `producer` 1, 2, 3, ….
pub fn chunks(g: &Graph, size: usize, producer: &str) -> Vec<(String, usize)> {
    let mut declared = 0usize; // poses 0..declared exist
    let mut out = Vec::new();
    for (n, part) in g.edges.chunks(size).enumerate() {
        let top = part.iter().map(|e| e.from.max(e.to)).max().unwrap_or(0);
        let variables: Vec<Value> = (declared..=top)
            .map(|k| {
                if k == 0 {
                    json!({"key": 0, "kind": "se2", "value": g.guesses[0], "fixed": true})
                } else {
                    json!({"key": k, "kind": "se2", "value": g.guesses[k]})
                }
            })
            .collect();
        declared = declared.max(top + 1);
        let factors: Vec<Value> = part.iter().map(factor).collect();
        let body = json!({"producer": producer, "producer_seq": n + 1,
                          "variables": variables, "factors": factors});
        out.push((body.to_string(), part.len()));
    }
    out
}
