//! Transports: thin adapters that turn requests into [`crate::service::Command`]s.

pub mod http;
pub mod zenoh;
