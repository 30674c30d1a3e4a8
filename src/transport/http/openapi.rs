//! The OpenAPI document of the HTTP routes, generated from the handlers' `#[utoipa::path]`
//! annotations and the wire types' `ToSchema` derives; served at `GET /v1/openapi.json` and
//! committed as `proto/v1/openapi.json` (`tests/api/openapi.rs` keeps the two equal).
//!
//! Here too: the shapes that exist only on the HTTP side (the error envelope, the path and job
//! parameters) and the error responses the handlers name; every command's reply is its own
//! named type in `api::command::replies`.

use utoipa::openapi::{ContentBuilder, Ref, RefOr, Response, ResponseBuilder};
use utoipa::{IntoParams, OpenApi, ToResponse, ToSchema};

use crate::api::ErrorBody;

/// Every error: `{"error": {...}}`, with the HTTP status in `status`.
#[derive(ToSchema)]
#[schema(as = Error)]
#[allow(dead_code)] // a schema only
pub struct ErrorResponse {
    error: ErrorBody,
}

/// The body of `POST /v1/sessions/{session}/factor_types`.
#[derive(ToSchema, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FactorTypesBody {
    pub factor_types: Vec<crate::factors::expression::FactorTypeDefinition>,
}

/// `POST /v1/jobs` as JSON: the solve's summary and the optimised values.
#[derive(ToSchema)]
#[allow(dead_code)]
pub struct JobResult {
    summary: crate::solver::Summary,
    /// The loop closures rejected as wrong (`outliers=auto`, a pose graph with loop closures).
    outliers: Option<crate::solver::GncReport>,
    /// The optimised variables (`job-result.schema.json`).
    #[schema(value_type = Object)]
    estimate: (),
}

/// The session a route works on.
#[derive(IntoParams)]
#[into_params(parameter_in = Path)]
#[allow(dead_code)]
pub struct SessionPath {
    /// Session name: 1–64 characters of `[A-Za-z0-9_-]`.
    session: String,
}

/// The producer a route reports on (exactly-once ingest).
#[derive(IntoParams)]
#[into_params(parameter_in = Path)]
#[allow(dead_code)]
pub struct ProducerPath {
    /// Producer id: 1–64 characters of `[A-Za-z0-9._-]`.
    producer: String,
}

/// `POST /v1/jobs`'s query parameters (`crate::service::jobs::JobParams`).
#[derive(IntoParams)]
#[into_params(parameter_in = Query)]
#[allow(dead_code)]
pub struct JobQuery {
    /// g2o | toro | bal (default: detected from the content).
    format: Option<String>,
    /// gn | lm | dogleg
    method: Option<String>,
    max_iterations: Option<u64>,
    /// none | chordal | auto
    init: Option<String>,
    /// e.g. huber:1.0
    robust: Option<String>,
    /// off (default) | auto: reject wrong loop closures by graduated non-convexity
    outliers: Option<String>,
    function_tolerance: Option<f64>,
    gradient_tolerance: Option<f64>,
    parameter_tolerance: Option<f64>,
    /// auto | sparse_cholesky | dense_schur | sparse_schur
    linear_solver: Option<String>,
    /// json (default) | g2o | tum | bal; `Accept: text/plain` means g2o.
    output: Option<String>,
}

/// Error responses: a name, its description, all with the [`ErrorResponse`] body.
macro_rules! error_responses {
    ($($name:ident: $description:literal;)*) => {$(
        pub struct $name;
        impl<'s> ToResponse<'s> for $name {
            fn response() -> (&'s str, RefOr<Response>) {
                let content = ContentBuilder::new()
                    .schema(Some(Ref::from_schema_name("Error")))
                    .build();
                let response = ResponseBuilder::new()
                    .description($description)
                    .content("application/json", content)
                    .build();
                (stringify!($name), response.into())
            }
        }
    )*};
}

error_responses! {
    BadRequest: "The request is malformed or names something impossible (`malformed_json`, \
        `invalid_field`, `invalid_query`, `unreadable_body`, `unknown_kind`, \
        `invalid_session_name`, `invalid_value`, `wrong_dimension`, `non_finite`, \
        `missing_noise`, `bad_information`, `unknown_factor_type`, …).";
    Unauthorized: "`unauthorized`: tokens are in force and the request has no valid \
        `Authorization: Bearer <token>` (with `WWW-Authenticate: Bearer`).";
    Forbidden: "`forbidden_origin`: a state-changing request (or a WebSocket upgrade) from a \
        web page of another origin than this server's or `http.allowed_origins`; \
        `operator_only`: `/metrics` with a token whose label is not in `auth.operators`.";
    NotFound: "`unknown_session` (also for a session of another token), `no_summary`, or \
        `no_route`.";
    Conflict: "`session_exists` / `session_on_disk` (create), or `session_corrupt` (writes to \
        a session whose files could not be recovered whole: read-only, DELETE removes it).";
    RequestTimeout: "`body_timeout` (field `body`): the request body arrived slower than \
        `http.body_min_bytes_per_s`, or, without a valid token, not within \
        `http.header_timeout_ms`.";
    PayloadTooLarge: "`body_too_large` (over `max_body_bytes`; without a valid token over 4096 \
        bytes, field `content-length` or `body`), `batch_too_large` (more items than \
        `limits.max_batch_items`), `list_too_long`, or a job over its memory limit.";
    UnsupportedMediaType: "`unsupported_media_type` (field `content-type`): this route reads \
        JSON and needs `Content-Type: application/json`.";
    Misdirected: "`forbidden_host` (field `host`): the Host header names neither a loopback \
        name, the listen host nor one of `http.allowed_hosts`.";
    Unprocessable: "Well-formed but invalid against the session's contents (`unknown_variable`, \
        `duplicate_variable`, `wrong_kind`, `unknown_factor`, `missing_value`, \
        `non_finite_residual`, `indeterminate_system`, …).";
    TooMany: "`too_many_pending`, `too_many_subscribers`, or `too_many_failures` (too many \
        wrong credentials from this address): retry after `Retry-After` seconds.";
    Unavailable: "The service is at capacity (`too_many_sessions`, `too_many_jobs`), shutting \
        down (`shutting_down`), the session is `recovering` from its journal, a journal write \
        failed (`journal_failed`), or a wait timed out (`solving`); `Retry-After` says when \
        to retry.";
}

/// The document's frame: its paths are added by [`super::routes()`] as it builds the router.
#[derive(OpenApi)]
#[openapi(
    info(
        title = "factord HTTP API",
        version = "1",
        description = "Pose-graph optimisation sessions over HTTP: add variables and factors \
            incrementally, read the estimate, stream solver events; plus one-shot batch jobs. \
            Generated from the server's types and handlers (`src/transport/http/openapi.rs`); \
            the JSON Schema files next to `proto/v1/openapi.json` describe the same messages. \
            Every error is `{\"error\": {code, message, field?, status, retry_after?}}` with \
            the HTTP status in `status`; 429 and 503 carry `Retry-After` (seconds). Unknown \
            JSON fields and query parameters are 400. Unknown paths are 404 `no_route`, known \
            paths with another method 405 `method_not_allowed`. With bearer tokens in force \
            every route but `/v1/health`, `/v1/openapi.json`, `/v1/docs` and the web view's \
            pages answers 401 without a valid token. The same operations exist on zenoh \
            (`command.schema.json`)."
    ),
    servers((url = "http://127.0.0.1:8080", description = "`factord serve` default listen address")),
    components(
        schemas(
            ErrorResponse,
            crate::api::Command,
            crate::api::Reply,
            crate::api::wire::SessionEvent,
            crate::api::wire::EstimateQuery,
        ),
        responses(
            BadRequest,
            Unauthorized,
            Forbidden,
            NotFound,
            Conflict,
            RequestTimeout,
            PayloadTooLarge,
            UnsupportedMediaType,
            Misdirected,
            Unprocessable,
            TooMany,
            Unavailable,
        )
    ),
    tags(
        (name = "service", description = "Health, metrics, this document."),
        (name = "sessions", description = "Create, list, inspect and delete sessions."),
        (name = "updates", description = "Batches of variables and factors, fusion messages; solving."),
        (name = "reads", description = "Estimate, summary, graph, marginals, event streams."),
        (name = "jobs", description = "One-shot optimisation of a whole graph file."),
        (name = "web", description = "The live web view and the API docs page: static pages \
            compiled into the binary that read the JSON API from the same origin."),
    )
)]
pub struct ApiDoc;

/// The document as served and committed: pretty JSON with a final newline.
pub fn document() -> String {
    let (_, api) = super::routes().split_for_parts();
    let mut text = api
        .to_pretty_json()
        .expect("the OpenAPI document serialises");
    text.push('\n');
    text
}

/// This document.
#[utoipa::path(
    get,
    path = "/v1/openapi.json",
    tag = "service",
    responses(
        (status = 200, description = "The OpenAPI 3.1 document of this server's HTTP routes.",
            content_type = "application/json", body = Object),
        (status = 421, response = Misdirected),
    )
)]
pub(super) async fn openapi_json() -> impl axum::response::IntoResponse {
    use std::sync::OnceLock;
    static DOCUMENT: OnceLock<String> = OnceLock::new();
    (
        [(axum::http::header::CONTENT_TYPE, "application/json")],
        DOCUMENT.get_or_init(document).as_str(),
    )
}
