//! factord: a sparse nonlinear least-squares back-end for pose graphs and factor graphs, and the
//! network service around it.
//!
//! Layers, lowest first; each imports only the ones below or beside it (`tests/layering.rs`,
//! docs/ARCHITECTURE.md): [`geometry`] and [`wire_number`] → [`variables`] → [`factors`] →
//! [`problem`] → [`solver`] → [`io`], [`fusion`] → [`api`] (wire types, commands, the typed
//! error) → [`journal`], [`runtime`] (pool, metrics) → [`session`] → [`service`] →
//! [`transport`] (HTTP and zenoh adapters over the one command API) → [`server`]. The solver core
//! has no network dependencies.

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
