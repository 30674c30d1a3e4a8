//! One-shot batch jobs: a whole graph file in, the optimised result out (the `POST /v1/jobs`
//! shortcut). A job runs on a thread of its own, computing only in turns lent by the worker
//! pool (see `pool`), and gives its turn back at the solver's fine-grained checkpoints.

use std::cell::{Cell, RefCell};
use std::ops::ControlFlow;
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

use serde::{Deserialize, Serialize};

use super::ServiceError;
use crate::api::catalogue::encode_variable_into;
use crate::api::wire::{VariableValue, WireValue};
use crate::api::ErrorKind;
use crate::factors::RobustKernel;
use crate::io::{self, Format};
use crate::runtime::pool::{PoolHandle, Turn};
use crate::solver::gnc::{loop_closures, GncOptions, GncReport};
use crate::solver::{
    self, Budget as _, Initialization, LinearSolverChoice, Method, SolverOptions, Summary,
};

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
    /// auto (default) | off: with auto and no `robust`, loop closures that do not fit are
    /// rejected by graduated non-convexity (pose graphs).
    pub outliers: Option<String>,
    pub function_tolerance: Option<f64>,
    pub gradient_tolerance: Option<f64>,
    pub parameter_tolerance: Option<f64>,
    /// auto | sparse_cholesky | dense_schur | sparse_schur | iterative_schur
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
    /// Reject wrong loop closures by graduated non-convexity (`outliers=auto`, no `robust`).
    reject_outliers: bool,
    pub output: JobOutput,
    /// The solve stops after this long (its turns added up) and answers with the best
    /// estimate it reached; the Summary's termination is then `interrupted`.
    max_solve: Duration,
    /// A job whose solve is estimated to need more is refused (413 `job_too_large`).
    max_memory_bytes: u64,
}

#[derive(Debug, Serialize)]
pub struct JobEstimate {
    pub variables: Vec<VariableValue>,
}

#[derive(Debug, Serialize)]
pub struct JobResult {
    pub summary: Summary,
    /// The loop closures graduated non-convexity rejected (`outliers=auto` on a pose graph with
    /// loop closures).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub outliers: Option<GncReport>,
    pub estimate: JobEstimate,
}

pub enum JobAnswer {
    Json(Box<JobResult>),
    Text(String),
}

fn bad_parameter(field: &str, message: String) -> ServiceError {
    ServiceError::bad_request("invalid_parameter", field, message)
}

/// The solver's options from the job's parameters (bundle adjustment leaves the gauge free, so
/// it starts from LM's damping).
fn solver_options(params: &JobParams, bal: bool) -> Result<SolverOptions, ServiceError> {
    let bad = bad_parameter;
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
                    "unknown linear solver `{l}` (auto, sparse_cholesky, dense_schur, sparse_schur, iterative_schur)"
                ),
            )
        })?;
    }
    options.validate().map_err(|(field, m)| bad(field, m))?;
    Ok(options)
}

/// The answer's form: g2o and TUM are for pose graphs, BAL for BAL input.
fn output(output: Option<&str>, bal: bool) -> Result<JobOutput, ServiceError> {
    let output = match output {
        None | Some("json") => JobOutput::Json,
        Some("g2o") => JobOutput::G2o,
        Some("tum") => JobOutput::Tum,
        Some("bal") => JobOutput::Bal,
        Some(o) => {
            return Err(bad_parameter(
                "output",
                format!("unknown output `{o}` (json, g2o, tum, bal)"),
            ))
        }
    };
    let pose_output = matches!(output, JobOutput::G2o | JobOutput::Tum);
    if (bal && pose_output) || (!bal && output == JobOutput::Bal) {
        return Err(bad_parameter(
            "output",
            "g2o and tum output is for pose graphs, bal output for bal input".into(),
        ));
    }
    Ok(output)
}

impl Job {
    /// `max_solve`: when the solve stops (see [`Job::max_solve`]); `max_memory_bytes`: the
    /// largest solve accepted (see [`Job::max_memory_bytes`]).
    pub fn new(
        text: String,
        params: JobParams,
        max_solve: Duration,
        max_memory_bytes: u64,
    ) -> Result<Self, ServiceError> {
        let bad = bad_parameter;
        let format = match params.format.as_deref() {
            None => None,
            Some("bal") => None,
            Some(f) => Some(Format::parse(f).ok_or_else(|| {
                bad(
                    "format",
                    format!("unknown format `{f}` (g2o, toro, gtsam, bal)"),
                )
            })?),
        };
        let bal = params.format.as_deref() == Some("bal");
        let options = solver_options(&params, bal)?;
        let robust = params
            .robust
            .as_deref()
            .map(RobustKernel::parse)
            .transpose()
            .map_err(|e| bad("robust", e.to_string()))?;
        let reject_outliers = match params.outliers.as_deref() {
            Some("auto") => robust.is_none() && !bal,
            None | Some("off") => false,
            Some(o) => {
                return Err(bad(
                    "outliers",
                    format!("unknown outliers mode `{o}` (auto, off)"),
                ))
            }
        };
        let output = output(params.output.as_deref(), bal)?;
        Ok(Self {
            text,
            format,
            bal,
            options,
            robust,
            reject_outliers,
            output,
            max_solve,
            max_memory_bytes,
        })
    }

    /// Starts the job on a thread of its own; it waits for a turn on the pool and the answer
    /// arrives on `reply`. `false` when the pool is shutting down (or no thread could start).
    pub fn submit(self, pool: &PoolHandle, reply: Reply) -> bool {
        if pool.is_stopping() {
            return false;
        }
        let pool = pool.clone();
        std::thread::Builder::new()
            .name("factord-job".into())
            .spawn(move || self.run(pool, reply))
            .is_ok()
    }

    fn run(self, pool: PoolHandle, reply: Reply) {
        // At shutdown the job is dropped unparsed, and with it `reply`: the caller hears so.
        let Some(turn) = pool.lend_turn() else { return };
        // Parsing cannot stop part way; the body size limit bounds it.
        let name = Path::new("request body");
        let parsed = if self.bal {
            io::bal::parse(name, &self.text).map(Parsed::Bal)
        } else {
            io::parse_text(&self.text, name, self.format).map(Parsed::PoseGraph)
        };
        drop(self.text);
        let mut graph = match parsed {
            Ok(graph) => graph,
            Err(e) => {
                let _ = reply.send(Err(ServiceError::bad_request(
                    "invalid_graph",
                    "body",
                    e.to_string(),
                )));
                return;
            }
        };
        if self.robust.is_some() {
            graph.problem_mut().set_robust_kernel(self.robust);
        }
        let budget = JobBudget {
            pool,
            turn: RefCell::new(Some(turn)),
            spent: Cell::new(Duration::ZERO),
            max_solve: self.max_solve,
            max_memory_bytes: self.max_memory_bytes,
        };
        let candidates = Some(self.reject_outliers)
            .filter(|&on| on)
            .map(|_| loop_closures(graph.problem_mut()))
            .filter(|c| c.iter().any(|&c| c));
        let result = match &candidates {
            Some(candidates) => solver::optimize_gnc(
                graph.problem_mut(),
                &self.options,
                &GncOptions::default(),
                candidates,
                &mut |_| budget.checkpoint(),
                &budget,
            )
            .map(|(summary, report)| (summary, Some(report))),
            None => solver::optimize_within(
                graph.problem_mut(),
                &self.options,
                &mut |_| budget.checkpoint(),
                &budget,
            )
            .map(|summary| (summary, None)),
        };
        let answer = match result {
            Ok((summary, outliers)) => Ok(Finished {
                graph,
                output: self.output,
            }
            .answer(summary, outliers)),
            Err(solver::SolverError::MemoryLimit {
                estimated, limit, ..
            }) => Err(ServiceError::new(
                ErrorKind::TooLarge,
                "job_too_large",
                format!(
                    "the job's solve would need about {} MiB of memory, more than limits.max_job_memory_bytes ({} MiB)",
                    estimated.div_ceil(1 << 20),
                    limit / (1 << 20)
                ),
            )
            .at("body")),
            // Stopped before its first step: at shutdown that is the shutdown's answer, as for a
            // job stopped later or one still queued (only a time limit too short for one cost
            // evaluation is the job's own failure).
            Err(solver::SolverError::Interrupted) if budget.pool.is_stopping() => Err(
                ServiceError::unavailable("shutting_down", "the job was stopped at shutdown", 5),
            ),
            Err(e) => Err(ServiceError::new(ErrorKind::Invalid, "solve_failed", e.to_string())),
        };
        // The turn goes back before the answer is sent: the caller may submit more at once.
        drop(budget);
        let _ = reply.send(answer);
    }
}

pub type Reply = tokio::sync::oneshot::Sender<Result<JobAnswer, ServiceError>>;

/// A job's solve budget: its time limit counts the turns it held; at every solver checkpoint it
/// stops (time limit, shutdown) or gives its turn back when it has held it for a time slice while
/// others wait, keeping every buffer of the solve for when its next turn comes.
struct JobBudget {
    pool: PoolHandle,
    /// `None` only when the pool shut down while the job waited for a turn.
    turn: RefCell<Option<Turn>>,
    /// Time held in earlier turns.
    spent: Cell<Duration>,
    max_solve: Duration,
    max_memory_bytes: u64,
}

impl JobBudget {
    fn spent(&self) -> Duration {
        self.spent.get()
            + self
                .turn
                .borrow()
                .as_ref()
                .map_or(Duration::ZERO, Turn::held)
    }
}

impl solver::Budget for JobBudget {
    fn checkpoint(&self) -> ControlFlow<()> {
        if self.pool.is_stopping() || self.spent() >= self.max_solve {
            return ControlFlow::Break(());
        }
        let mut turn = self.turn.borrow_mut();
        let Some(held) = turn.take_if(|t| t.should_yield()) else {
            return if turn.is_some() {
                ControlFlow::Continue(())
            } else {
                ControlFlow::Break(())
            };
        };
        self.spent.set(self.spent.get() + held.held());
        *turn = held.requeue();
        if turn.is_some() {
            ControlFlow::Continue(())
        } else {
            ControlFlow::Break(())
        }
    }

    fn remaining(&self) -> Option<Duration> {
        Some(self.max_solve.saturating_sub(self.spent()))
    }

    fn max_memory_bytes(&self) -> Option<u64> {
        Some(self.max_memory_bytes)
    }
}

/// A solved job, to be answered in the requested output.
struct Finished {
    graph: Parsed,
    output: JobOutput,
}

impl Finished {
    fn answer(self, summary: Summary, outliers: Option<GncReport>) -> JobAnswer {
        match (&self.graph, self.output) {
            (Parsed::PoseGraph(g), JobOutput::G2o) => JobAnswer::Text(io::g2o::to_string(g)),
            (Parsed::PoseGraph(g), JobOutput::Tum) => {
                JobAnswer::Text(io::tum::to_string_with_ids(g))
            }
            (Parsed::Bal(b), JobOutput::Bal) => JobAnswer::Text(io::bal::to_string(b)),
            _ => {
                let values = self.graph.values();
                // One buffer for every value: each is then copied inline into its wire value.
                let mut encoded = Vec::new();
                let variables = self
                    .graph
                    .keys()
                    .iter()
                    .map(|&key| {
                        let v = values
                            .get(key)
                            .expect("vertex order lists the graph's keys");
                        encode_variable_into(v, &mut encoded);
                        VariableValue {
                            key,
                            kind: v.kind().into(),
                            value: WireValue::from_slice(&encoded),
                            changed: 0,
                            stamp: None,
                        }
                    })
                    .collect();
                JobAnswer::Json(Box::new(JobResult {
                    summary,
                    outliers,
                    estimate: JobEstimate { variables },
                }))
            }
        }
    }
}

impl super::Service {
    /// Runs a batch job on the pool; 503 when `max_jobs` are already in flight.
    pub async fn run_job(
        &self,
        text: String,
        params: JobParams,
    ) -> Result<JobAnswer, ServiceError> {
        let job = Job::new(
            text,
            params,
            Duration::from_millis(self.limits.max_solve_ms),
            self.limits.max_job_memory_bytes,
        )?;
        let previous = self.jobs_in_flight.fetch_add(1, Ordering::SeqCst);
        let _slot = JobSlot(&self.jobs_in_flight);
        if previous >= self.limits.max_jobs {
            return Err(ServiceError::unavailable(
                "too_many_jobs",
                format!(
                    "{} batch jobs are already running or queued",
                    self.limits.max_jobs
                ),
                1,
            ));
        }
        let (tx, rx) = tokio::sync::oneshot::channel();
        if !job.submit(&self.pool.handle(), tx) {
            return Err(ServiceError::unavailable(
                "shutting_down",
                "the service is shutting down",
                5,
            ));
        }
        rx.await.map_err(|_| {
            ServiceError::unavailable("shutting_down", "the job was dropped at shutdown", 5)
        })?
    }
}

/// Counts a job in flight until it is dropped, whatever way `run_job` ends.
struct JobSlot<'a>(&'a AtomicUsize);

impl Drop for JobSlot<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::SeqCst);
    }
}
