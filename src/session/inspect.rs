//! Read-only views of a session beyond its estimate: the drawable graph (what the web view
//! shows) and marginal covariances of selected variables.

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::time::Instant;

use super::engine::{Engine, Window};
use super::{MirrorEntry, Session, State};
use crate::api::catalogue::{self, Shape};
use crate::api::wire::{DrawnVariable, Graph, MarginalCovariance, Marginals, MarginalsQuery};
use crate::api::ErrorKind;
use crate::api::ServiceError;
use crate::problem::{Chi2Scratch, Key};
use crate::solver::marginals::{self, MarginalsError};
use crate::variables::{position_covariance, Variable};

/// Most variables one marginals request may name (each costs a solve per tangent direction).
pub const MAX_MARGINAL_KEYS: usize = 256;

/// World position of a wire value of `kind` (kinds come from the catalogue; every one of them
/// has a position).
pub(super) fn position(kind: &str, value: &[f64]) -> [f64; 3] {
    let codec = catalogue::variable_codec(kind).expect("mirror kinds come from the catalogue");
    let variable = (codec.decode)(value).expect("mirror values were encoded by the codec");
    variable
        .position()
        .expect("every catalogue kind has a position")
}

fn shape(kind: &str) -> Shape {
    catalogue::variable_codec(kind)
        .expect("mirror kinds come from the catalogue")
        .shape
}

/// The edge a factor over `keys` draws: only factors between two poses (odometry, loop
/// closures), not observations of landmarks.
pub(super) fn edge(mirror: &BTreeMap<Key, MirrorEntry>, keys: &[Key]) -> Option<[Key; 2]> {
    let [a, b] = keys else { return None };
    let is_pose = |k: &Key| mirror.get(k).is_some_and(|e| shape(e.kind) == Shape::Pose);
    (is_pose(a) && is_pose(b)).then_some([*a, *b])
}

/// Each edge's χ² contribution `ρ(‖R e‖²)` at the estimate, in the order of `st.mirror.edges`; none
/// while a solve holds the problem, for an edge still queued, or where it cannot be evaluated.
fn edge_chi2(st: &State) -> Vec<Option<f64>> {
    let Some(problem) = &st.model.problem else {
        return vec![None; st.mirror.edges.len()];
    };
    let mut by_id = HashMap::with_capacity(st.mirror.edges.len());
    let mut scratch = Chi2Scratch::default();
    for (f, id) in problem.factors().iter().zip(&st.model.factor_ids) {
        if !st.mirror.edges.contains_key(id) {
            continue;
        }
        if let Ok(chi2) = scratch.chi2(f, &problem.values) {
            by_id.insert(*id, chi2);
        }
    }
    // Closures held out as possibly wrong: what they would add (a rejected one's is large).
    by_id.extend(st.outliers.held_chi2(&problem.values));
    st.mirror
        .edges
        .keys()
        .map(|id| by_id.get(id).copied().filter(|c| c.is_finite()))
        .collect()
}

impl Session {
    pub fn graph(&self) -> Graph {
        match &self.engine {
            Engine::Graph(graph) => self.problem_graph(graph.dimension),
            Engine::Window(window) => self.window_graph(window),
        }
    }

    /// A graph session's variables (poses and landmarks) and the factors between two poses.
    fn problem_graph(&self, dimension: u8) -> Graph {
        let st = self.lock();
        let (mut poses, mut points) = (Vec::new(), Vec::new());
        for (&key, entry) in &st.mirror.entries {
            let drawn = DrawnVariable {
                key,
                position: position(entry.kind, &entry.value),
                initial: entry.initial,
            };
            match shape(entry.kind) {
                Shape::Pose => poses.push(drawn),
                Shape::Landmark => points.push(drawn),
            }
        }
        Graph {
            session: self.name.clone(),
            kind: self.kind.name.into(),
            sequence: st.mirror.sequence,
            dimension,
            poses,
            points,
            edges: st.mirror.edges.values().copied().collect(),
            edge_chi2: edge_chi2(&st),
        }
    }

    /// A sliding window's keyframes (marginalised ones stay, fixed) and the factors between two
    /// of them. The window keeps no initial guesses: `initial` is the current position.
    fn window_graph(&self, window: &Window) -> Graph {
        let sequence = self.lock().mirror.sequence;
        let guard = window.window.lock().unwrap_or_else(|p| p.into_inner());
        let (mut poses, mut edges) = (Vec::new(), Vec::new());
        if let Some(window) = guard.as_ref() {
            let values = &window.problem().values;
            for v in 0..values.len() {
                if let Some(position) = values.variable(v).position() {
                    poses.push(DrawnVariable {
                        key: values.key(v),
                        position,
                        initial: position,
                    });
                }
            }
            poses.sort_by_key(|p| p.key);
            for f in window.problem().factors() {
                if let &[a, b] = f.variables() {
                    edges.push([values.key(a), values.key(b)]);
                }
            }
        }
        Graph {
            session: self.name.clone(),
            kind: self.kind.name.into(),
            sequence,
            dimension: 3,
            poses,
            points: Vec::new(),
            edges,
            edge_chi2: Vec::new(),
        }
    }

    /// Marginal covariances at the current estimate. `Ok(None)` when a solve holds the problem
    /// and no factorisation of the current estimate is cached: ask again after it.
    ///
    /// Runs the factorisation on the calling thread (call it off the async runtime). Batches
    /// that arrive meanwhile are queued as during a solve, so they are never refused for it.
    pub fn marginals(
        self: &Arc<Self>,
        query: &MarginalsQuery,
    ) -> Result<Option<Marginals>, ServiceError> {
        let start = Instant::now();
        if query.keys.is_empty() || query.keys.len() > MAX_MARGINAL_KEYS {
            return Err(ServiceError::bad_request(
                "invalid_value",
                "keys",
                format!(
                    "name between 1 and {MAX_MARGINAL_KEYS} variables, got {}",
                    query.keys.len()
                ),
            ));
        }
        let graph = match &self.engine {
            Engine::Graph(graph) => graph,
            Engine::Window(window) => return self.window_marginals(window, query, start).map(Some),
        };
        // Lock order: the cached factorisation, then the state.
        let mut cache = graph.marginals.lock().unwrap_or_else(|p| p.into_inner());
        let st = self.lock();
        if st.schedule.phase.is_deleted() {
            return Err(self.gone());
        }
        let variables = queried_variables(&st, &query.keys)?;
        let version = (st.mirror.sequence, st.results.solves);
        let reused = matches!(&*cache, Some((v, _)) if *v == version);
        if !reused {
            let Some(factorized) = self.factorize(st)? else {
                return Ok(None);
            };
            graph.marginals_bytes.store(
                factorized.memory_bytes(),
                std::sync::atomic::Ordering::Relaxed,
            );
            *cache = Some((version, factorized));
        } else {
            drop(st);
        }
        let (_, held) = cache.as_mut().expect("filled above");
        let covariance = held.covariance(&query.keys).map_err(|e| match e {
            MarginalsError::UnknownVariable { key } | MarginalsError::Repeated { key } => {
                ServiceError::internal(format!(
                    "variable {key}: the factorisation disagrees with the estimate"
                ))
            }
        })?;
        let variables = query
            .keys
            .iter()
            .zip(&variables)
            .enumerate()
            .map(|(i, (&key, variable))| {
                marginal_of(
                    key,
                    variable.as_ref(),
                    &covariance.block(i, i),
                    held.gauge_fixed.binary_search(&key).is_ok(),
                )
            })
            .collect();
        let joint = query
            .joint
            .then(|| rows(&covariance.joint, covariance.dimension()));
        Ok(Some(Marginals {
            session: self.name.clone(),
            sequence: version.0,
            solves: version.1,
            variables,
            joint,
            gauge_fixed: held.gauge_fixed.clone(),
            reused_factorization: reused,
            factorize_seconds: held.factorize_seconds,
            seconds: start.elapsed().as_secs_f64(),
        }))
    }
}

impl Session {
    /// Factorises the problem at the current estimate, lending it out of the state meanwhile
    /// (batches that arrive are queued as during a solve). `None` when a solve holds it or is
    /// queued for it.
    fn factorize(
        self: &Arc<Self>,
        mut st: std::sync::MutexGuard<'_, State>,
    ) -> Result<Option<marginals::Marginals>, ServiceError> {
        // While the problem is here its values are the estimate clients read (the mirror).
        // No solve takes the problem while it is out.
        if !st.schedule.phase.lend() {
            return Ok(None);
        }
        let (problem, index) = st.model.take();
        drop(st);
        let factorized = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            marginals::Marginals::new(&problem)
        }));
        let mut st = self.lock();
        self.hand_back(&mut st, problem, index);
        st.schedule.phase.give_back();
        self.maybe_schedule(&mut st);
        drop(st);
        factorized
            .map_err(|_| ServiceError::internal("the factorisation panicked"))?
            .map_err(|e| {
                ServiceError::new(ErrorKind::Invalid, "indeterminate_system", e.to_string())
            })
            .map(Some)
    }
}

/// The variables a marginals query names, decoded from the mirror: each existing, none twice.
fn queried_variables(st: &State, keys: &[Key]) -> Result<Vec<Box<dyn Variable>>, ServiceError> {
    let mut variables = Vec::with_capacity(keys.len());
    for (i, key) in keys.iter().enumerate() {
        match st.mirror.entries.get(key) {
            Some(entry) => variables.push(entry.decode()),
            None => {
                return Err(ServiceError::invalid(
                    "unknown_variable",
                    format!("keys[{i}]"),
                    format!("variable {key} does not exist"),
                ))
            }
        }
        if keys[..i].contains(key) {
            return Err(ServiceError::bad_request(
                "invalid_value",
                format!("keys[{i}]"),
                format!("variable {key} is named twice"),
            ));
        }
    }
    Ok(variables)
}

/// One variable's answer: its tangent covariance (`block`, row-major) and its position's.
pub(super) fn marginal_of(
    key: Key,
    variable: &dyn Variable,
    block: &[f64],
    fixed: bool,
) -> MarginalCovariance {
    MarginalCovariance {
        key,
        kind: variable.kind().into(),
        fixed,
        covariance: rows(block, variable.tangent_dim()),
        position_covariance: position_covariance(variable, block).map(|c| rows(&c, 3)),
    }
}

pub(super) fn rows(row_major: &[f64], n: usize) -> Vec<Vec<f64>> {
    row_major.chunks(n.max(1)).map(<[f64]>::to_vec).collect()
}
