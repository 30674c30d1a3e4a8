//! factord: a sparse nonlinear least-squares back-end for pose graphs and factor graphs.
//!
//! Layers, each usable on its own: [`geometry`] (Lie groups) → [`problem`] (variables, values) and
//! [`factors`] (residuals with analytic Jacobians) → [`solver`] (normal equations, sparse Cholesky,
//! GN/LM/Dogleg, initialisation, Summary) → [`io`] (g2o, TORO, TUM). The solver core has no network
//! dependencies.

pub mod factors;
pub mod geometry;
pub mod io;
pub mod problem;
pub mod solver;
