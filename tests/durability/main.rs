//! The journal: kill -9 and restart, damaged files, snapshots, delete and create again, exactly-once producers, the state-directory lock.
//!
//! One test binary per area (each file below was a binary of its own): a change to the library
//! relinks a handful of binaries instead of sixty. Run one file's tests with
//! `cargo test --release --test durability <file>::`.

#[path = "../common/mod.rs"]
mod common;

mod ba_given_snapshot;
mod durability;
mod durability_damage;
mod durability_delete_create;
mod durability_history;
mod durability_snapshot;
mod exactly_once;
mod exactly_once_faults;
mod group_commit;
mod state_dir_lock;
