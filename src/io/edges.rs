//! Adding a file's edges to its problem, and a start for graphs given as edges only.
//!
//! SE-Sync's `CSAIL.g2o` and GTSAM's `w20000.txt` have no vertex lines. Their vertices are
//! placed along a breadth-first spanning tree of the edges from the smallest id (at the
//! origin), each by composing the measurement of the tree edge that reaches it. Where the
//! consecutive edges are odometry, this is chaining the odometry, the start GTSAM's examples
//! use. `factord solve`'s default chordal initialisation (`--init auto`) then replaces it;
//! `--init none` starts from it.

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::path::Path;

use nalgebra::DMatrix;

use super::{problem_error, IoError};
use crate::factors::Factor;
use crate::problem::{Key, Problem};
use crate::variables::Variable;

/// One edge record, built, with where it came from.
pub(crate) struct Edge<'a> {
    pub factor: Box<dyn Factor>,
    pub information: DMatrix<f64>,
    pub label: String,
    pub path: &'a Path,
    pub line: usize,
}

/// Adds `edges` to `problem`. When the files had no vertices (`problem` has no variables), the
/// vertices the edges name are placed first (module doc), the tree's root at `origin`; their
/// keys in ascending order are returned (the vertex order for writing the graph back).
pub(crate) fn add_edges(
    problem: &mut Problem,
    edges: Vec<Edge>,
    origin: Box<dyn Variable>,
    file: &Path,
) -> Result<Vec<Key>, IoError> {
    let mut placed = Vec::new();
    if problem.values.is_empty() && !edges.is_empty() {
        let start = spanning_tree_start(&edges, origin, file)?;
        placed = start.keys().copied().collect();
        for (key, value) in start {
            problem
                .add_variable(key, value)
                .expect("each key placed once");
        }
    }
    for edge in edges {
        problem
            .add_factor(edge.factor, &edge.information, None, edge.label)
            .map_err(|e| problem_error(edge.path, edge.line, e))?;
    }
    Ok(placed)
}

/// Every vertex `edges` name, placed along a breadth-first spanning tree from the smallest.
fn spanning_tree_start(
    edges: &[Edge],
    origin: Box<dyn Variable>,
    file: &Path,
) -> Result<BTreeMap<Key, Box<dyn Variable>>, IoError> {
    let mut incident: BTreeMap<Key, Vec<usize>> = BTreeMap::new();
    for (e, edge) in edges.iter().enumerate() {
        for &key in edge.factor.keys() {
            incident.entry(key).or_default().push(e);
        }
    }
    let root = *incident.keys().next().expect("edges name vertices");
    let mut placed: BTreeMap<Key, Box<dyn Variable>> = BTreeMap::new();
    placed.insert(root, origin);
    let mut queue = VecDeque::from([root]);
    while let Some(key) = queue.pop_front() {
        for &e in &incident[&key] {
            let factor = edges[e].factor.as_ref();
            let keys = factor.keys();
            for (target, &other) in keys.iter().enumerate() {
                if placed.contains_key(&other) {
                    continue;
                }
                let known: Vec<Option<&dyn Variable>> = keys
                    .iter()
                    .map(|k| placed.get(k).map(|v| v.as_ref()))
                    .collect();
                if let Some(value) = factor.predict(&known, target) {
                    placed.insert(other, value);
                    queue.push_back(other);
                }
            }
        }
    }
    let unplaced: BTreeSet<Key> = incident
        .keys()
        .filter(|k| !placed.contains_key(k))
        .copied()
        .collect();
    if let Some(first) = unplaced.first() {
        return Err(IoError::Invalid {
            file: file.to_path_buf(),
            reason: format!(
                "the file has no vertices and its edges do not connect vertex {first} (and {} \
                 more) to vertex {root}: a start can only be made for a connected graph",
                unplaced.len() - 1
            ),
        });
    }
    Ok(placed)
}
