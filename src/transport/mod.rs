//! Transports: thin adapters that turn requests into [`crate::service::Command`]s.

pub mod http;
mod web;
pub mod zenoh;
