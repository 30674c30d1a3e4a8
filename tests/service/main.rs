//! The service as a user drives it: sessions over HTTP, streams, exports, user-defined factors, marginals, landmarks, fusion sessions and the web pages.
//!
//! One test binary per area (each file below was a binary of its own): a change to the library
//! relinks a handful of binaries instead of sixty. Run one file's tests with
//! `cargo test --release --test service <file>::`.

#[path = "../common/mod.rs"]
mod common;

mod ba_stream;
mod config_sessions;
mod export;
mod factor_type_memory;
mod fusion_service;
mod gnss_factor;
mod incremental;
mod landing_slices;
mod landmarks_2d;
mod landmarks_3d_ranges;
mod latency;
mod marginals;
mod outliers;
mod producer_list;
mod robot_streams;
mod robot_streams_cost;
mod robot_streams_late;
mod robots;
mod service;
mod session_threads;
mod stream_lag;
mod user_factors;
mod web_operators;
mod web_view;
mod wrong_closures_job;
