//! HTTP adapter (axum): REST routes onto [`crate::service::Command`]s, Server-Sent Events and
//! WebSockets for the streams, and the batch-job shortcut, behind our own connection loop.
//! Errors are `{"error": {"code", "message", "field"?, "status"}}` with the matching status code
//! (and `Retry-After` under back-pressure).
//!
//! - `mod.rs`: the router and the order of its layers;
//! - `errors`: the JSON error body, for our errors and for those axum and hyper answer themselves;
//! - `handlers`: one handler per REST route, each a [`crate::service::Command`] run as the caller;
//! - `streams`: the event stream (SSE) and the WebSocket;
//! - `auth`: bearer tokens, and the caller each request carries;
//! - `guard`: cross-site requests (Host, Origin, Content-Type);
//! - `listener` and `connection_io`: accepting connections, their cap, reserve and timeouts.

pub mod auth;
mod connection_io;
mod errors;
pub mod guard;
mod handlers;
pub mod listener;
mod streams;

pub use errors::HttpError;

use std::sync::Arc;

use axum::extract::DefaultBodyLimit;
use axum::routing::{get, post};
use axum::Router;
use tower_http::trace::TraceLayer;

use crate::service::Service;

use errors::{json_errors, method_not_allowed, not_found};
use handlers::*;
use streams::{events, websocket};

/// The router, with request bodies limited to `max_body_bytes`, bearer tokens required when
/// `tokens` is given, then cross-site requests refused by `guard` (after the token check, so a
/// caller without a token learns nothing but 401).
pub fn router(
    service: Arc<Service>,
    max_body_bytes: usize,
    tokens: Option<Arc<auth::Tokens>>,
    guard: Arc<guard::HttpGuard>,
) -> Router {
    let routes = Router::new()
        .route("/v1/health", get(health))
        .route("/metrics", get(metrics))
        .route("/v1/sessions", post(create_session).get(list_sessions))
        .route("/v1/sessions/{session}", get(stats).delete(delete_session))
        .route("/v1/sessions/{session}/batches", post(apply_batch))
        .route("/v1/sessions/{session}/fusion", post(fusion))
        .route("/v1/sessions/{session}/optimize", post(optimize))
        .route(
            "/v1/sessions/{session}/auto_optimize",
            axum::routing::put(set_auto_optimize),
        )
        .route("/v1/sessions/{session}/estimate", get(estimate))
        .route("/v1/sessions/{session}/summary", get(summary))
        .route("/v1/sessions/{session}/cancel", post(cancel))
        .route("/v1/sessions/{session}/events", get(events))
        .route("/v1/sessions/{session}/ws", get(websocket))
        .route("/v1/sessions/{session}/graph", get(graph))
        .route("/v1/sessions/{session}/marginals", get(marginals))
        .route("/v1/jobs", post(job))
        .merge(super::web::routes())
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        .layer(DefaultBodyLimit::max(max_body_bytes))
        .layer(axum::middleware::from_fn_with_state(guard, guard::guard));
    // Every request carries its `Caller` from here on; a handler without one fails closed.
    let routes = match tokens {
        Some(tokens) => routes.layer(axum::middleware::from_fn_with_state(
            tokens,
            auth::require_token,
        )),
        None => routes.layer(axum::middleware::from_fn(auth::trust_everyone)),
    };
    routes
        .layer(axum::middleware::from_fn(json_errors))
        .layer(TraceLayer::new_for_http())
        .with_state(service)
}
