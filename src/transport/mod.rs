//! Transports: thin adapters that turn requests into [`crate::api::Command`]s, and the one
//! client the crate ships (the robot side of the fusion experiment over zenoh).

pub mod fusion_client;
pub mod http;
mod ros2;
mod web;
pub mod zenoh;
