//! One-shot batch jobs: a whole graph file in, the optimised result out (the `POST /v1/jobs`
//! shortcut). The job runs on the worker pool like any solve.

use std::ops::ControlFlow;
use std::path::Path;
use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::pool::{PoolHandle, TIME_SLICE};
use super::ServiceError;
use crate::factors::RobustKernel;
use crate::io::{self, Format};
use crate::session::catalogue::encode_variable;
use crate::session::wire::VariableValue;
use crate::solver::{self, Initialization, LinearSolverChoice, Method, SolverOptions, Summary};

/// Job parameters (HTTP query parameters).
#[derive(Clone, Debug, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct JobParams {
    /// g2o | toro (default: detected from the content).
    pub format: Option<String>,
    /// gn | lm | dogleg
    pub method: Option<String>,
    pub max_iterations: Option<usize>,
    /// none | chordal | auto
    pub init: Option<String>,
    /// e.g. huber:1.0
    pub robust: Option<String>,
    pub function_tolerance: Option<f64>,
    pub gradient_tolerance: Option<f64>,
    pub parameter_tolerance: Option<f64>,
    /// auto | sparse_cholesky | dense_schur | sparse_schur
    pub linear_solver: Option<String>,
    /// json (default) | g2o | tum
    pub output: Option<String>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum JobOutput {
    Json,
    G2o,
    Tum,
    Bal,
}

/// What a job parsed: a pose graph or a bundle-adjustment problem.
enum Parsed {
    PoseGraph(io::PoseGraph),
    Bal(io::bal::BalProblem),
}

impl Parsed {
    fn problem_mut(&mut self) -> &mut crate::problem::Problem {
        match self {
            Self::PoseGraph(g) => &mut g.problem,
            Self::Bal(b) => &mut b.problem,
        }
    }

    /// The keys in the order the input listed them (vertices; BAL cameras then points).
    fn keys(&self) -> &[crate::problem::Key] {
        match self {
            Self::PoseGraph(g) => &g.vertex_order,
            Self::Bal(b) => b.problem.values.keys(),
        }
    }

    fn values(&self) -> &crate::problem::Values {
        match self {
            Self::PoseGraph(g) => &g.problem.values,
            Self::Bal(b) => &b.problem.values,
        }
    }
}

/// A validated job, ready to run.
pub struct Job {
    text: String,
    format: Option<Format>,
    bal: bool,
    options: SolverOptions,
    robust: Option<RobustKernel>,
    pub output: JobOutput,
    /// The solve stops after this long (its preempted slices added up) and answers with the
    /// best estimate it reached; the Summary's termination is then `interrupted`.
    max_solve: std::time::Duration,
}

#[derive(Debug, Serialize)]
pub struct JobEstimate {
    pub variables: Vec<VariableValue>,
}

#[derive(Debug, Serialize)]
pub struct JobResult {
    pub summary: Summary,
    pub estimate: JobEstimate,
}

pub enum JobAnswer {
    Json(Box<JobResult>),
    Text(String),
}

impl Job {
    /// `max_solve`: when the solve stops (see [`Job::max_solve`]).
    pub fn new(
        text: String,
        params: JobParams,
        max_solve: std::time::Duration,
    ) -> Result<Self, ServiceError> {
        let bad = |field: &str, m: String| ServiceError::bad_request("invalid_parameter", field, m);
        let format =
            match params.format.as_deref() {
                None => None,
                Some("bal") => None,
                Some(f) => Some(Format::parse(f).ok_or_else(|| {
                    bad("format", format!("unknown format `{f}` (g2o, toro, bal)"))
                })?),
            };
        let bal = params.format.as_deref() == Some("bal");
        // Bundle adjustment leaves the gauge free: it needs LM's damping by default.
        let mut options = if bal {
            SolverOptions::bundle_adjustment()
        } else {
            SolverOptions::default()
        };
        if let Some(m) = &params.method {
            options.method = Method::parse(m)
                .ok_or_else(|| bad("method", format!("unknown method `{m}` (gn, lm, dogleg)")))?;
        }
        if let Some(n) = params.max_iterations {
            options.max_iterations = n;
        }
        if let Some(init) = &params.init {
            options.initialization = match init.as_str() {
                "none" => Initialization::None,
                "chordal" => Initialization::Chordal,
                "auto" => Initialization::Auto,
                _ => {
                    return Err(bad(
                        "init",
                        format!("unknown initialisation `{init}` (none, chordal, auto)"),
                    ))
                }
            };
        }
        if let Some(t) = params.function_tolerance {
            options.function_tolerance = t;
        }
        if let Some(t) = params.gradient_tolerance {
            options.gradient_tolerance = t;
        }
        if let Some(t) = params.parameter_tolerance {
            options.parameter_tolerance = t;
        }
        if let Some(l) = &params.linear_solver {
            options.linear_solver = LinearSolverChoice::parse(l).ok_or_else(|| {
                bad(
                    "linear_solver",
                    format!(
                        "unknown linear solver `{l}` (auto, sparse_cholesky, dense_schur, sparse_schur)"
                    ),
                )
            })?;
        }
        options.validate().map_err(|(field, m)| bad(field, m))?;
        let robust = params
            .robust
            .as_deref()
            .map(RobustKernel::parse)
            .transpose()
            .map_err(|e| bad("robust", e.to_string()))?;
        let output = match params.output.as_deref() {
            None | Some("json") => JobOutput::Json,
            Some("g2o") => JobOutput::G2o,
            Some("tum") => JobOutput::Tum,
            Some("bal") => JobOutput::Bal,
            Some(o) => {
                return Err(bad(
                    "output",
                    format!("unknown output `{o}` (json, g2o, tum, bal)"),
                ))
            }
        };
        let pose_output = matches!(output, JobOutput::G2o | JobOutput::Tum);
        if (bal && pose_output) || (!bal && output == JobOutput::Bal) {
            return Err(bad(
                "output",
                "g2o and tum output is for pose graphs, bal output for bal input".into(),
            ));
        }
        Ok(Self {
            text,
            format,
            bal,
            options,
            robust,
            output,
            max_solve,
        })
    }

    /// Queues the job on the pool; the answer arrives on `reply`. Like session solves, a long
    /// job yields its worker after a time slice when others wait, and continues at the back of
    /// the queue. `false` when the pool is shutting down.
    pub fn submit(self, pool: &PoolHandle, reply: Reply) -> bool {
        let handle = pool.clone();
        pool.submit(Box::new(move || {
            let name = Path::new("request body");
            let parsed = if self.bal {
                io::bal::parse(name, &self.text).map(Parsed::Bal)
            } else {
                io::parse_text(&self.text, name, self.format).map(Parsed::PoseGraph)
            };
            match parsed {
                Ok(mut graph) => {
                    if self.robust.is_some() {
                        graph.problem_mut().set_robust_kernel(self.robust);
                    }
                    let running = Running {
                        graph,
                        options: self.options,
                        output: self.output,
                        previous: None,
                        max_solve: self.max_solve,
                        spent: std::time::Duration::ZERO,
                    };
                    running.slice(handle, reply);
                }
                Err(e) => {
                    let _ = reply.send(Err(ServiceError::bad_request(
                        "invalid_graph",
                        "body",
                        e.to_string(),
                    )));
                }
            }
        }))
    }
}

pub type Reply = tokio::sync::oneshot::Sender<Result<JobAnswer, ServiceError>>;

struct Running {
    graph: Parsed,
    options: SolverOptions,
    output: JobOutput,
    /// What the earlier slices did.
    previous: Option<Summary>,
    max_solve: std::time::Duration,
    /// Time the earlier slices took.
    spent: std::time::Duration,
}

impl Running {
    fn slice(mut self, pool: PoolHandle, reply: Reply) {
        let start = Instant::now();
        let mut preempted = false;
        let (spent, max_solve) = (self.spent, self.max_solve);
        let result = solver::optimize(self.graph.problem_mut(), &self.options, &mut |_| {
            if pool.is_stopping() || spent + start.elapsed() >= max_solve {
                return ControlFlow::Break(());
            }
            if pool.waiting() > 0 && start.elapsed() > TIME_SLICE {
                preempted = true;
                return ControlFlow::Break(());
            }
            ControlFlow::Continue(())
        });
        let summary = match result {
            Ok(summary) => merge(self.previous.take(), summary),
            Err(e) => {
                let _ = reply.send(Err(ServiceError::new(422, "solve_failed", e.to_string())));
                return;
            }
        };
        if preempted {
            self.spent += start.elapsed();
            self.previous = Some(summary);
            self.options.initialization = Initialization::None;
            // At shutdown the task (and with it `reply`) is dropped: the caller hears so.
            let handle = pool.clone();
            pool.submit(Box::new(move || self.slice(handle, reply)));
            return;
        }
        let _ = reply.send(Ok(self.answer(summary)));
    }

    fn answer(self, summary: Summary) -> JobAnswer {
        match (&self.graph, self.output) {
            (Parsed::PoseGraph(g), JobOutput::G2o) => JobAnswer::Text(io::g2o::to_string(g)),
            (Parsed::PoseGraph(g), JobOutput::Tum) => JobAnswer::Text(io::tum::to_string(g)),
            (Parsed::Bal(b), JobOutput::Bal) => JobAnswer::Text(io::bal::to_string(b)),
            _ => {
                let values = self.graph.values();
                let variables = self
                    .graph
                    .keys()
                    .iter()
                    .map(|&key| {
                        let v = values
                            .get(key)
                            .expect("vertex order lists the graph's keys");
                        VariableValue {
                            key,
                            kind: v.kind().into(),
                            value: encode_variable(v),
                            changed: 0,
                        }
                    })
                    .collect();
                JobAnswer::Json(Box::new(JobResult {
                    summary,
                    estimate: JobEstimate { variables },
                }))
            }
        }
    }
}

/// One Summary for a solve that ran in several slices.
fn merge(previous: Option<Summary>, mut next: Summary) -> Summary {
    let Some(p) = previous else { return next };
    next.given_options = p.given_options;
    next.initial_chi2 = p.initial_chi2;
    next.initialized_chi2 = p.initialized_chi2;
    next.used.initialization = p.used.initialization;
    for r in &mut next.iteration_log {
        r.iteration += p.iterations;
    }
    let mut log = p.iteration_log;
    log.append(&mut next.iteration_log);
    next.iteration_log = log;
    next.iterations += p.iterations;
    next.successful_steps += p.successful_steps;
    next.unsuccessful_steps += p.unsuccessful_steps;
    next.solve_seconds += p.solve_seconds;
    let (t, q) = (&mut next.timings, &p.timings);
    t.preprocess_seconds += q.preprocess_seconds;
    t.initialization_seconds += q.initialization_seconds;
    t.linearize_seconds += q.linearize_seconds;
    t.factorize_seconds += q.factorize_seconds;
    t.linear_solve_seconds += q.linear_solve_seconds;
    t.evaluate_seconds += q.evaluate_seconds;
    next
}
