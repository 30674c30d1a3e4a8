//! Transports: thin adapters that turn requests into [`crate::api::Command`]s.

pub mod http;
mod ros2;
mod web;
pub mod zenoh;
