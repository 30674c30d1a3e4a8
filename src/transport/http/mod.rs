//! HTTP adapter (axum): REST routes onto [`crate::service::Command`]s, Server-Sent Events and
//! WebSockets for the streams, and the batch-job shortcut, behind our own connection loop.
//! Errors are `{"error": {"code", "message", "field"?, "status"}}` with the matching status code
//! (and `Retry-After` under back-pressure).
//!
//! - `mod.rs`: the router and the order of its layers;
//! - `errors`: the JSON error body, for our errors and for those axum and hyper answer themselves;
//! - `handlers`: one handler per REST route, each a [`crate::service::Command`] run as the caller;
//! - `streams`: the event stream (SSE) and the WebSocket;
//! - `openapi`: the OpenAPI document generated from the handlers, served at `/v1/openapi.json`;
//! - `auth`: bearer tokens (or the web view's cookie, for reads), and the caller each request
//!   carries;
//! - `login`, `web_sessions`: the web view's login, which exchanges a token for that cookie,
//!   naming a server-side login session;
//! - `throttle`: failed authentications per peer;
//! - `guard`: cross-site requests (Host, Origin, Content-Type);
//! - `listener` and `connection_io`: accepting connections, their cap, reserve and timeouts;
//! - `admission`: which connections get a slot, and which give theirs up to newcomers;
//! - `body_limits`: how fast a body must arrive, and how large one without a credential may be.

mod admission;
pub mod auth;
mod body_limits;
mod connection_io;
mod errors;
pub mod fleet_caller;
pub mod forward;
pub mod guard;
mod handlers;
pub mod listener;
mod login;
pub mod openapi;
mod streams;
mod throttle;
mod web_sessions;

pub use errors::HttpError;

use std::sync::Arc;

use axum::extract::DefaultBodyLimit;
use axum::Router;
use tower_http::trace::TraceLayer;
use utoipa::OpenApi;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use crate::service::Service;

use errors::{json_errors, method_not_allowed, not_found};
use handlers::*;
use streams::{__path_events, __path_websocket, events, websocket};

/// Every route with its operations' documentation: the router and the OpenAPI document
/// ([`openapi::document`]) are both made from this, so neither has a route the other lacks.
pub fn routes() -> OpenApiRouter<Arc<Service>> {
    OpenApiRouter::with_openapi(openapi::ApiDoc::openapi())
        .routes(routes!(health))
        .routes(routes!(metrics))
        .routes(routes!(create_session, list_sessions))
        .routes(routes!(stats, delete_session))
        .routes(routes!(apply_batch))
        .routes(routes!(fusion))
        .routes(routes!(optimize))
        .routes(routes!(set_auto_optimize))
        .routes(routes!(define_factor_types))
        .routes(routes!(estimate))
        .routes(routes!(list_producers))
        .routes(routes!(list_robots))
        .routes(routes!(list_outliers))
        .routes(routes!(producer_status))
        .routes(routes!(summary))
        .routes(routes!(cancel))
        .routes(routes!(events))
        .routes(routes!(websocket))
        .routes(routes!(graph))
        .routes(routes!(marginals))
        .routes(routes!(history))
        .routes(routes!(login::login))
        .routes(routes!(login::logout))
        .routes(routes!(job))
        .routes(routes!(openapi::openapi_json))
        .merge(super::web::routes())
}

/// The router, with request bodies limited to `max_body_bytes`, bearer tokens required when
/// `tokens` is given, then cross-site requests refused by `guard` (after the token check, so a
/// caller without a token learns nothing but 401).
pub fn router(
    service: Arc<Service>,
    max_body_bytes: usize,
    tokens: Option<Arc<auth::Tokens>>,
    guard: Arc<guard::HttpGuard>,
) -> Router {
    let (routes, _) = routes().split_for_parts();
    let routes = routes
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        .layer(DefaultBodyLimit::max(max_body_bytes));
    // In a fleet, requests for other instances' sessions go there (after the checks below).
    let routes = match forward::Forwarder::for_fleet(&service, max_body_bytes, tokens.clone()) {
        Some(f) => routes.layer(axum::middleware::from_fn_with_state(f, forward::forward)),
        None => routes,
    };
    let routes = routes.layer(axum::middleware::from_fn_with_state(guard, guard::guard));
    // Every request carries its `Caller` from here on; a handler without one fails closed.
    let routes = match tokens {
        Some(tokens) => routes.layer(axum::middleware::from_fn_with_state(
            tokens,
            auth::require_token,
        )),
        None => routes.layer(axum::middleware::from_fn(auth::trust_everyone)),
    };
    // Before the token check: a request another member forwarded runs as the caller it
    // asserts, when the assertion's proof holds.
    let routes = match service.fleet() {
        Some(_) => routes.layer(axum::middleware::from_fn_with_state(
            Arc::clone(&service),
            fleet_caller::accept_asserted,
        )),
        None => routes,
    };
    routes
        .layer(axum::middleware::from_fn(json_errors))
        .layer(TraceLayer::new_for_http())
        .with_state(service)
}
