//! The library used directly (no server): solvers, datasets against the reference optima, readers, the incremental engine, fusion.
//!
//! One test binary per area (each file below was a binary of its own): a change to the library
//! relinks a handful of binaries instead of sixty. Run one file's tests with
//! `cargo test --release --test library <file>::`.

#[path = "../common/mod.rs"]
mod common;

mod bad_input;
mod bal;
mod datasets;
mod direct_ba;
mod edges_only;
mod fusion;
mod incremental_engine;
mod incremental_engine_3d;
mod innovation_gate;
mod preintegration_gtsam;
mod warm_start;
mod wrong_closures;
