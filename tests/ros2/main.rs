//! ROS 2 over rmw_zenoh: topics in and out, message bounds, and ROS robots against a fleet.
//!
//! One test binary per area (each file below was a binary of its own): a change to the library
//! relinks a handful of binaries instead of sixty. Run one file's tests with
//! `cargo test --release --test ros2 <file>::`.

#[path = "../common/mod.rs"]
mod common;

mod fleet_ros2;
mod robot_tf;
mod ros2;
mod ros2_bounds;
