//! The command API's rules seen through HTTP: every input rule of docs/INPUT_CATALOGUE.md, limits and budgets, OpenAPI and the factor schema, authentication, tenants and the HTTP guards.
//!
//! One test binary per area (each file below was a binary of its own): a change to the library
//! relinks a handful of binaries instead of sixty. Run one file's tests with
//! `cargo test --release --test api <file>::`.

#[path = "../common/mod.rs"]
mod common;

mod auth;
mod connection_limits;
mod factor_schema;
mod hardening_rules;
mod http_guard;
mod input_catalogue;
mod input_catalogue_jobs;
mod input_catalogue_reads;
mod input_catalogue_service;
mod job_budget;
mod job_budget_ba;
mod limits;
mod login_hardening;
mod openapi;
mod oversize_memory;
mod python_types;
mod session_budget;
mod tenant_isolation;
mod unauthenticated_limits;
