//! Sliding-window fusion: marginalisation of old states into linear priors (and, next, IMU
//! pre-integration and the window estimator of the `sliding_window` session kind).

pub mod experiment;
pub mod marginalize;
pub mod window;

pub use marginalize::{marginalize, MarginalizeError};
