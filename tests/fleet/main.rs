//! Fleets of real instances over zenoh in every topology: placement, failover, the rpc gateway, membership proofs, robots, ACLs and routers.
//!
//! One test binary per area (each file below was a binary of its own): a change to the library
//! relinks a handful of binaries instead of sixty. Run one file's tests with
//! `cargo test --release --test fleet <file>::`.

#[path = "../common/mod.rs"]
mod common;

mod fleet;
mod fleet_budget;
mod fleet_login;
mod fleet_owner;
mod fleet_robot_streams;
mod fleet_robots;
mod fleet_rpc_once;
mod fleet_stopped_host;
mod fleet_trust;
mod zenoh_acl;
mod zenoh_router;
