//! The live web view: static pages compiled into the binary (no CDN, nothing to install), which
//! read the JSON API and the session's event stream from the same origin.
//!
//! `/` lists sessions with the server's health (and a login form when tokens are on);
//! `/sessions/<id>` draws the trajectory, initial guess, residual-coloured edges, covariance
//! ellipses, point cloud, a live convergence plot and the session's timeline, event log and
//! rejected inputs, with export links; `/v1/docs` lists the API's operations, parameters and
//! schemas from `/v1/openapi.json`. The pages are plain HTML, CSS and JS in `web/`.

use std::sync::Arc;

use axum::extract::{Path, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use crate::service::fleet::Route;
use crate::service::{Caller, Service};

const INDEX: &str = include_str!("web/index.html");
const SESSION: &str = include_str!("web/session.html");
const SCRIPT: &str = include_str!("web/factord.js");
const STYLE: &str = include_str!("web/factord.css");
const PLOTS: &str = include_str!("web/plots.js");
const OPERATOR: &str = include_str!("web/operator.js");
const DOCS: &str = include_str!("web/docs.html");
const DOCS_SCRIPT: &str = include_str!("web/docs.js");
const HTML: &str = "text/html; charset=utf-8";

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

#[utoipa::path(get, path = "/sessions/{session}", tag = "web",
    params(crate::transport::http::openapi::SessionPath),
    responses(
        (status = 200, description = "The session page (HTML).", content_type = "text/html", body = String),
        (status = 404, description = "No such session (HTML).", content_type = "text/html", body = String)))]
/// The session page, or a 404 page naming the session when there is none (the page itself
/// would only find out from its first request). With tokens the page is open to anyone and the
/// browser sends no token for it, so it is served whatever the name: the API calls it makes
/// answer 404 for a session the token may not see, and the page says so; answering 404 here
/// would tell strangers which sessions exist. In a fleet a session another instance owns is
/// not here to look up (the list links every session on the instance it came from): its page
/// is served, and its API calls reach the owner.
pub(crate) async fn session_page(
    State(service): State<Arc<Service>>,
    axum::Extension(caller): axum::Extension<Caller>,
    Path(session): Path<String>,
) -> Response {
    let elsewhere = service.route(&session) != Route::Local;
    let exists =
        !caller.sees_everything() || elsewhere || service.session_as(&caller, &session).is_ok();
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

/// The session list.
#[utoipa::path(get, path = "/", tag = "web",
    responses((status = 200, description = "The session list page.", content_type = "text/html", body = String)))]
pub(crate) async fn index_page() -> impl IntoResponse {
    page(INDEX, HTML)
}

/// The web view's script.
#[utoipa::path(get, path = "/assets/factord.js", tag = "web",
    responses((status = 200, description = "JavaScript.", content_type = "text/javascript", body = String)))]
pub(crate) async fn script() -> impl IntoResponse {
    page(SCRIPT, "text/javascript; charset=utf-8")
}

/// The web view's plots: convergence and the session's timeline.
#[utoipa::path(get, path = "/assets/plots.js", tag = "web",
    responses((status = 200, description = "JavaScript.", content_type = "text/javascript", body = String)))]
pub(crate) async fn plots_script() -> impl IntoResponse {
    page(PLOTS, "text/javascript; charset=utf-8")
}

/// The web view's operator panels: login, health, history, rejections, exports, ellipses.
#[utoipa::path(get, path = "/assets/operator.js", tag = "web",
    responses((status = 200, description = "JavaScript.", content_type = "text/javascript", body = String)))]
pub(crate) async fn operator_script() -> impl IntoResponse {
    page(OPERATOR, "text/javascript; charset=utf-8")
}

/// The web view's style sheet.
#[utoipa::path(get, path = "/assets/factord.css", tag = "web",
    responses((status = 200, description = "CSS.", content_type = "text/css", body = String)))]
pub(crate) async fn style() -> impl IntoResponse {
    page(STYLE, "text/css; charset=utf-8")
}

/// The API's documentation: operations, parameters and schemas, read from `/v1/openapi.json`.
#[utoipa::path(get, path = "/v1/docs", tag = "web",
    responses((status = 200, description = "The API docs page.", content_type = "text/html", body = String)))]
pub(crate) async fn docs_page() -> impl IntoResponse {
    page(DOCS, HTML)
}

/// The docs page's script.
#[utoipa::path(get, path = "/assets/docs.js", tag = "web",
    responses((status = 200, description = "JavaScript.", content_type = "text/javascript", body = String)))]
pub(crate) async fn docs_script() -> impl IntoResponse {
    page(DOCS_SCRIPT, "text/javascript; charset=utf-8")
}

/// The pages, documented (see `http::routes`).
pub fn routes() -> OpenApiRouter<Arc<Service>> {
    OpenApiRouter::new()
        .routes(routes!(index_page))
        .routes(routes!(session_page))
        .routes(routes!(script))
        .routes(routes!(plots_script))
        .routes(routes!(operator_script))
        .routes(routes!(style))
        .routes(routes!(docs_page))
        .routes(routes!(docs_script))
}
