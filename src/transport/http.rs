//! HTTP adapter (axum): REST routes onto [`Command`]s, Server-Sent Events for the streams, and
//! the batch-job shortcut. Errors are `{"error": {"code", "message", "field"?, "status"}}` with
//! the matching status code (and `Retry-After` under back-pressure).

use std::convert::Infallible;
use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::rejection::BytesRejection;
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::extract::{DefaultBodyLimit, Path, RawQuery, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use futures_util::Stream;
use serde::Deserialize;
use tokio::sync::broadcast::error::RecvError;
use tower_http::trace::TraceLayer;

use crate::service::jobs::{JobAnswer, JobParams};
use crate::service::{
    parse_json, parse_json_within, parse_query, Command, Reply, Service, ServiceError,
};
use crate::session::fusion::FusionBatch;
use crate::session::wire::{AutoOptimize, Batch, CreateSession, EstimateQuery};

type Shared = State<Arc<Service>>;

/// The router, with request bodies limited to `max_body_bytes`, bearer tokens required when
/// `tokens` is given, then cross-site requests refused by `guard` (after the token check, so a
/// caller without a token learns nothing but 401).
pub fn router(
    service: Arc<Service>,
    max_body_bytes: usize,
    tokens: Option<Arc<super::auth::Tokens>>,
    guard: Arc<super::http_guard::HttpGuard>,
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
        .layer(axum::middleware::from_fn_with_state(
            guard,
            super::http_guard::guard,
        ));
    // Every request carries its `Caller` from here on; a handler without one fails closed.
    let routes = match tokens {
        Some(tokens) => routes.layer(axum::middleware::from_fn_with_state(
            tokens,
            super::auth::require_token,
        )),
        None => routes.layer(axum::middleware::from_fn(super::auth::trust_everyone)),
    };
    routes
        .layer(axum::middleware::from_fn(json_errors))
        .layer(TraceLayer::new_for_http())
        .with_state(service)
}

/// Errors axum's own extractors answer in plain text (a path segment that is not UTF-8, a
/// WebSocket request without its upgrade headers) become our JSON error body, so every API
/// error has the same shape.
async fn json_errors(request: axum::extract::Request, next: axum::middleware::Next) -> Response {
    let api = request.uri().path().starts_with("/v1/");
    let response = next.run(request).await;
    let status = response.status();
    let plain = response
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("text/plain"));
    if !api || !plain || !(status.is_client_error() || status.is_server_error()) {
        return response;
    }
    let bytes = axum::body::to_bytes(response.into_body(), 64 << 10)
        .await
        .unwrap_or_default();
    let message = String::from_utf8_lossy(&bytes).into_owned();
    let code = if status.is_client_error() {
        "invalid_request"
    } else {
        "internal"
    };
    HttpError(ServiceError::new(status.as_u16(), code, message)).into_response()
}

/// An error as an HTTP response.
pub struct HttpError(ServiceError);

impl From<ServiceError> for HttpError {
    fn from(e: ServiceError) -> Self {
        Self(e)
    }
}

impl IntoResponse for HttpError {
    fn into_response(self) -> Response {
        let body = self.0.body;
        crate::service::metrics::count_rejection(&body);
        let status = StatusCode::from_u16(body.status).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR);
        let retry = body.retry_after;
        let mut response = (status, Json(serde_json::json!({ "error": body }))).into_response();
        if let Some(seconds) = retry {
            response
                .headers_mut()
                .insert(header::RETRY_AFTER, HeaderValue::from(seconds));
        }
        response
    }
}

type HttpResult = Result<Response, HttpError>;

fn body_error(rejection: BytesRejection) -> HttpError {
    let status = rejection.status();
    let code = if status == StatusCode::PAYLOAD_TOO_LARGE {
        "body_too_large"
    } else {
        "unreadable_body"
    };
    HttpError(ServiceError::new(status.as_u16(), code, rejection.body_text()).at("body"))
}

fn query<T: serde::de::DeserializeOwned>(raw: RawQuery) -> Result<T, HttpError> {
    Ok(parse_query(raw.0.as_deref().unwrap_or(""))?)
}

/// The request's caller, left by the auth layer (see `router`).
type Caller = axum::Extension<crate::service::Caller>;

async fn run(
    service: &Service,
    caller: &Caller,
    command: Command,
    status: StatusCode,
) -> HttpResult {
    let reply = service.execute_as(&caller.0, command).await?;
    Ok((status, Json(reply)).into_response())
}

/// Prometheus text exposition.
async fn metrics(State(service): Shared) -> Response {
    (
        [(
            header::CONTENT_TYPE,
            "text/plain; version=0.0.4; charset=utf-8",
        )],
        crate::service::metrics::render(&service),
    )
        .into_response()
}

async fn health(State(service): Shared, caller: Caller) -> HttpResult {
    run(&service, &caller, Command::Health, StatusCode::OK).await
}

async fn list_sessions(State(service): Shared, caller: Caller) -> HttpResult {
    run(&service, &caller, Command::ListSessions, StatusCode::OK).await
}

async fn create_session(
    State(service): Shared,
    caller: Caller,
    body: Result<Bytes, BytesRejection>,
) -> HttpResult {
    let request: CreateSession = parse_json(&body.map_err(body_error)?)?;
    let command = Command::CreateSession(request);
    run(&service, &caller, command, StatusCode::CREATED).await
}

async fn stats(State(service): Shared, caller: Caller, Path(session): Path<String>) -> HttpResult {
    run(
        &service,
        &caller,
        Command::GetStats { session },
        StatusCode::OK,
    )
    .await
}

async fn delete_session(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
) -> HttpResult {
    run(
        &service,
        &caller,
        Command::DeleteSession { session },
        StatusCode::OK,
    )
    .await
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct WaitParam {
    #[serde(default)]
    wait: bool,
}

async fn apply_batch(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
    raw: RawQuery,
    body: Result<Bytes, BytesRejection>,
) -> HttpResult {
    let WaitParam { wait } = query(raw)?;
    let max_items = service.limits().max_batch_items;
    let batch: Batch = parse_json_within(&body.map_err(body_error)?, max_items)?;
    run(
        &service,
        &caller,
        Command::ApplyBatch {
            session,
            batch,
            wait,
        },
        StatusCode::OK,
    )
    .await
}

async fn fusion(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
    body: Result<Bytes, BytesRejection>,
) -> HttpResult {
    let max_items = service.limits().max_batch_items;
    let batch: FusionBatch = parse_json_within(&body.map_err(body_error)?, max_items)?;
    let messages = batch.messages;
    run(
        &service,
        &caller,
        Command::Fusion { session, messages },
        StatusCode::OK,
    )
    .await
}

async fn optimize(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
    raw: RawQuery,
) -> HttpResult {
    let WaitParam { wait } = query(raw)?;
    let status = if wait {
        StatusCode::OK
    } else {
        StatusCode::ACCEPTED
    };
    run(
        &service,
        &caller,
        Command::Optimize { session, wait },
        status,
    )
    .await
}

async fn set_auto_optimize(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
    body: Result<Bytes, BytesRejection>,
) -> HttpResult {
    let auto_optimize: AutoOptimize = parse_json(&body.map_err(body_error)?)?;
    run(
        &service,
        &caller,
        Command::SetAutoOptimize {
            session,
            auto_optimize,
        },
        StatusCode::OK,
    )
    .await
}

async fn estimate(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
    raw: RawQuery,
) -> HttpResult {
    let EstimateQuery { since, from, to } = query(raw)?;
    run(
        &service,
        &caller,
        Command::GetEstimate {
            session,
            since,
            from,
            to,
        },
        StatusCode::OK,
    )
    .await
}

async fn graph(State(service): Shared, caller: Caller, Path(session): Path<String>) -> HttpResult {
    run(
        &service,
        &caller,
        Command::GetGraph { session },
        StatusCode::OK,
    )
    .await
}

/// `?keys=3,17&joint=true`: keys as one comma-separated list.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct MarginalsParams {
    keys: String,
    #[serde(default)]
    joint: bool,
}

async fn marginals(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
    raw: RawQuery,
) -> HttpResult {
    let MarginalsParams { keys, joint } = query(raw)?;
    let keys = keys
        .split(',')
        .enumerate()
        .map(|(i, k)| {
            k.trim().parse::<u64>().map_err(|_| {
                ServiceError::bad_request(
                    "invalid_query",
                    format!("keys[{i}]"),
                    format!("`{k}` is not a variable key (a non-negative integer)"),
                )
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    run(
        &service,
        &caller,
        Command::GetMarginals {
            session,
            keys,
            joint,
        },
        StatusCode::OK,
    )
    .await
}

async fn summary(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
) -> HttpResult {
    let command = Command::GetStats { session };
    let Reply::Stats(stats) = service.execute_as(&caller.0, command).await? else {
        unreachable!("GetStats answers with Stats");
    };
    match stats.last_summary {
        Some(summary) => Ok(Json(summary).into_response()),
        None => {
            Err(ServiceError::new(404, "no_summary", "this session has not been solved yet").into())
        }
    }
}

async fn cancel(State(service): Shared, caller: Caller, Path(session): Path<String>) -> HttpResult {
    run(
        &service,
        &caller,
        Command::Cancel { session },
        StatusCode::OK,
    )
    .await
}

/// Server-Sent Events: every session event, named by its topic (`acks`, `stats`, `poses`,
/// `summary`, `errors`); `lagged` when this client fell behind and missed some.
async fn events(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, HttpError> {
    let session = service.session_as(&caller.0, &session)?;
    let receiver = session.subscribe_limited()?;
    drop(session);
    let stream = futures_util::stream::unfold(receiver, |mut rx| async move {
        let event = match rx.recv().await {
            Ok(event) => Event::default()
                .event(event.topic())
                .json_data(&*event)
                .unwrap_or_else(|_| {
                    Event::default()
                        .event("errors")
                        .data("unserialisable event")
                }),
            Err(RecvError::Lagged(missed)) => Event::default()
                .event("lagged")
                .data(format!("{{\"missed\":{missed}}}")),
            Err(RecvError::Closed) => return None,
        };
        Some((Ok(event), rx))
    });
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()))
}

/// WebSocket: the same events as the SSE stream (one JSON text message each, tagged by `type`;
/// `{"type": "lagged", "missed": n}` when this client fell behind), and text messages from the
/// client are batches for the session, acknowledged by the `ack` event or rejected by an `error`
/// event naming the problem.
async fn websocket(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
    upgrade: WebSocketUpgrade,
) -> Result<Response, HttpError> {
    let events = service
        .session_as(&caller.0, &session)?
        .subscribe_limited()?;
    let caller = caller.0;
    Ok(upgrade.on_upgrade(move |socket| serve_websocket(socket, service, caller, session, events)))
}

async fn serve_websocket(
    mut socket: WebSocket,
    service: Arc<Service>,
    caller: crate::service::Caller,
    session: String,
    mut events: tokio::sync::broadcast::Receiver<Arc<crate::session::wire::SessionEvent>>,
) {
    loop {
        tokio::select! {
            event = events.recv() => {
                let text = match event {
                    Ok(event) => serde_json::to_string(&*event).expect("events serialise"),
                    Err(RecvError::Lagged(missed)) => format!("{{\"type\":\"lagged\",\"missed\":{missed}}}"),
                    Err(RecvError::Closed) => break,
                };
                if socket.send(Message::Text(text.into())).await.is_err() {
                    break;
                }
            }
            incoming = socket.recv() => {
                let bytes = match incoming {
                    Some(Ok(Message::Text(text))) => text.as_bytes().to_vec(),
                    Some(Ok(Message::Binary(bytes))) => bytes.to_vec(),
                    Some(Ok(_)) => continue,
                    Some(Err(_)) | None => break,
                };
                // Accepted batches are acknowledged on the event stream; rejections too.
                if service.deliver(&caller, &session, "batch", &bytes).await.is_err() {
                    break; // the session is gone
                }
            }
        }
    }
}

async fn job(
    State(service): Shared,
    headers: HeaderMap,
    raw: RawQuery,
    body: Result<Bytes, BytesRejection>,
) -> HttpResult {
    let mut params: JobParams = query(raw)?;
    let body = body.map_err(body_error)?;
    let text = String::from_utf8(body.to_vec()).map_err(|_| {
        ServiceError::bad_request(
            "unreadable_body",
            "body",
            "the graph file is not UTF-8 text",
        )
    })?;
    let wants_text = headers
        .get(header::ACCEPT)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("text/plain"));
    if wants_text && params.output.is_none() {
        params.output = Some("g2o".into());
    }
    match service.run_job(text, params).await? {
        JobAnswer::Json(result) => Ok(Json(result).into_response()),
        JobAnswer::Text(text) => {
            Ok(([(header::CONTENT_TYPE, "text/plain; charset=utf-8")], text).into_response())
        }
    }
}

async fn not_found() -> HttpError {
    HttpError(ServiceError::new(
        404,
        "no_route",
        "no such route (the API is under /v1/)",
    ))
}

async fn method_not_allowed() -> HttpError {
    HttpError(ServiceError::new(
        405,
        "method_not_allowed",
        "this route does not take that method",
    ))
}
