//! The live web view: static pages compiled into the binary (no CDN, nothing to install), which
//! read the JSON API and the session's event stream from the same origin.
//!
//! `/` lists sessions; `/sessions/<id>` draws the trajectory, initial guess, loop closures, point
//! cloud and a live convergence plot. The pages are plain HTML, CSS and JS in `web/`.

use std::sync::Arc;

use axum::extract::{Path, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;

use crate::service::{Caller, Service};

const INDEX: &str = include_str!("web/index.html");
const SESSION: &str = include_str!("web/session.html");
const SCRIPT: &str = include_str!("web/factord.js");
const STYLE: &str = include_str!("web/factord.css");

fn page(body: &'static str, content_type: &'static str) -> impl IntoResponse {
    (
        [
            (header::CONTENT_TYPE, content_type),
            // The pages change with the binary; always revalidate.
            (header::CACHE_CONTROL, "no-cache"),
        ],
        body,
    )
}

/// The session page, or a 404 page naming the session when there is none (the page itself
/// would only find out from its first request). With tokens the page is open to anyone and the
/// browser sends no token for it, so it is served whatever the name: the API calls it makes
/// answer 404 for a session the token may not see, and the page says so; answering 404 here
/// would tell strangers which sessions exist.
async fn session_page(
    State(service): State<Arc<Service>>,
    axum::Extension(caller): axum::Extension<Caller>,
    Path(session): Path<String>,
) -> Response {
    let exists = !caller.sees_everything() || service.session_as(&caller, &session).is_ok();
    match exists {
        true => page(SESSION, "text/html; charset=utf-8").into_response(),
        false => (
            StatusCode::NOT_FOUND,
            [(header::CONTENT_TYPE, "text/html; charset=utf-8")],
            format!(
                "<!doctype html><title>factord: no session</title><p>There is no session <code>{}</code>. <a href=\"/\">All sessions</a></p>",
                escape_html(&session)
            ),
        )
            .into_response(),
    }
}

fn escape_html(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

pub fn routes() -> Router<Arc<Service>> {
    let html = "text/html; charset=utf-8";
    Router::new()
        .route("/", get(move || async move { page(INDEX, html) }))
        .route("/sessions/{session}", get(session_page))
        .route(
            "/assets/factord.js",
            get(|| async { page(SCRIPT, "text/javascript; charset=utf-8") }),
        )
        .route(
            "/assets/factord.css",
            get(|| async { page(STYLE, "text/css; charset=utf-8") }),
        )
}
