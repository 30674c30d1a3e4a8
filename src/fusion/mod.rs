//! Sliding-window fusion: the window estimator of the `sliding_window` session kind, the
//! marginalisation of old states into linear priors (the EuRoC experiment built on it lives in
//! `eval/`, outside the library).
//!
//! Layer 5: imports `geometry` (IMU pre-integration lives there), `factors`, `problem`, `solver`
//! and `io`; the session drives it from above.

pub mod envelope;
pub mod gauss_newton;
pub mod marginalize;
pub mod window;

pub use marginalize::{marginalize, MarginalizeError};
