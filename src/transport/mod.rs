//! Transports: thin adapters that turn requests into [`crate::service::Command`]s.

pub mod auth;
mod connection_io;
pub mod http;
pub mod http_guard;
pub mod listener;
mod web;
pub mod zenoh;
