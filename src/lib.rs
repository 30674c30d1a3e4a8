//! factord: a sparse nonlinear least-squares back-end for pose graphs and factor graphs, and the
//! network service around it.
//!
//! Layers, each usable on its own: [`geometry`] (Lie groups) → [`problem`] (variables, values) and
//! [`factors`] (residuals with analytic Jacobians) → [`solver`] (normal equations, sparse Cholesky,
//! GN/LM/Dogleg, initialisation, Summary) → [`io`] (g2o, TORO, TUM). The solver core has no network
//! dependencies. On top: [`session`] (an incrementally growing problem per client), [`service`]
//! (session registry, worker pool, the one command API) and [`transport`] (HTTP and zenoh adapters
//! over that API).

pub mod api;
pub mod factors;
pub mod fusion;
pub mod geometry;
pub mod io;
pub mod journal;
pub mod problem;
pub mod runtime;
pub mod server;
pub mod service;
pub mod session;
pub mod solver;
pub mod transport;
pub mod variables;
pub mod wire_number;
