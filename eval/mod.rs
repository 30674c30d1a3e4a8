//! Evaluation harnesses that are not part of the service: the course's EuRoC fusion experiment
//! (its inputs, the in-process window run, APE as evo reports it), the robot-side zenoh client
//! that streams it to a running server, and the Cholesky timing of `factord bench-cholesky`.
//! They use the library as any client does; the `factord` binary (`fusion-eval`,
//! `bench-cholesky`), the tests and the benches include this directory
//! (`#[path = ".../eval/mod.rs"] mod eval;`), so the service library carries none of it.
#![allow(dead_code)]

pub mod cholesky_bench;
pub mod experiment;
pub mod fusion_client;
