//! One-shot batch jobs: a whole graph file in, the optimised result out (the `POST /v1/jobs`
//! shortcut). The job runs on the worker pool like any solve.

use std::ops::ControlFlow;
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::pool::PoolHandle;
use super::ServiceError;
use crate::factors::RobustKernel;
use crate::io::{self, Format};
use crate::session::catalogue::encode_variable;
use crate::session::wire::VariableValue;
use crate::solver::{self, Initialization, Method, SolverOptions, Summary};

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
    /// json (default) | g2o | tum
    pub output: Option<String>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum JobOutput {
    Json,
    G2o,
    Tum,
}

/// A validated job, ready to run.
pub struct Job {
    text: String,
    format: Option<Format>,
    options: SolverOptions,
    robust: Option<RobustKernel>,
    pub output: JobOutput,
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
    pub fn new(text: String, params: JobParams) -> Result<Self, ServiceError> {
        let bad = |field: &str, m: String| ServiceError::bad_request("invalid_parameter", field, m);
        let format = match params.format.as_deref() {
            None => None,
            Some("bal") => {
                return Err(ServiceError::bad_request(
                    "unsupported_format",
                    "format",
                    "bundle-adjustment (BAL) jobs are not supported yet; formats: g2o, toro",
                ))
            }
            Some(f) => Some(
                Format::parse(f)
                    .ok_or_else(|| bad("format", format!("unknown format `{f}` (g2o, toro)")))?,
            ),
        };
        let mut options = SolverOptions::default();
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
            Some(o) => {
                return Err(bad(
                    "output",
                    format!("unknown output `{o}` (json, g2o, tum)"),
                ))
            }
        };
        Ok(Self {
            text,
            format,
            options,
            robust,
            output,
        })
    }

    /// Parses and solves (on a pool worker); stops early when the pool shuts down.
    pub fn run(self, pool: &PoolHandle) -> Result<JobAnswer, ServiceError> {
        let mut graph = io::parse_text(&self.text, Path::new("request body"), self.format)
            .map_err(|e| ServiceError::bad_request("invalid_graph", "body", e.to_string()))?;
        if self.robust.is_some() {
            graph.problem.set_robust_kernel(self.robust);
        }
        let summary = solver::optimize(&mut graph.problem, &self.options, &mut |_| {
            if pool.is_stopping() {
                ControlFlow::Break(())
            } else {
                ControlFlow::Continue(())
            }
        })
        .map_err(|e| ServiceError::new(422, "solve_failed", e.to_string()))?;
        Ok(match self.output {
            JobOutput::G2o => JobAnswer::Text(io::g2o::to_string(&graph)),
            JobOutput::Tum => JobAnswer::Text(io::tum::to_string(&graph)),
            JobOutput::Json => {
                let values = &graph.problem.values;
                let variables = graph
                    .vertex_order
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
        })
    }
}
