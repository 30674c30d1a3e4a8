//! One handler per REST route: decode the request, run its command as the caller, render the reply.

use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::rejection::BytesRejection;
use axum::extract::{Path, RawQuery, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::Deserialize;

use crate::api::export::Export;
use crate::api::fusion::FusionBatch;
use crate::api::wire::{AutoOptimize, Batch, CreateSession, EstimateQuery};
use crate::api::ErrorKind;
use crate::api::{
    AfterFields, ApplyBatch, Cancel, DefineFactorTypes, DeleteSession, Fusion, GetGraph,
    GetHistory, GetMarginals, GetStats, ListOutliers, ListProducers, ListRobots, Optimize,
    ProducerQuery, SetAutoOptimize,
};
use crate::service::jobs::{JobAnswer, JobParams};
use crate::service::ServiceError;
use crate::service::{parse_json, parse_json_within, Command, Recording, Reply, Service};

pub(super) type Shared = State<Arc<Service>>;
use super::errors::{body_error, query, HttpError, HttpResult};
use super::openapi::*;

/// The request's caller, left by the auth layer (see `router`).
pub(super) type Caller = axum::Extension<crate::service::Caller>;

/// Every route's one way into the service: `command` run as the request's caller, a refused
/// input kept in its session's history ([`Recording::History`]).
pub(super) async fn run(
    service: &Service,
    caller: &Caller,
    command: Command,
) -> Result<Reply, HttpError> {
    Ok(service
        .execute(&caller.0, command, Recording::History)
        .await?)
}

/// A reply as JSON with `status`.
fn json(status: StatusCode, reply: Reply) -> HttpResult {
    Ok((status, Json(reply)).into_response())
}

/// Prometheus text exposition.
#[utoipa::path(get, path = "/metrics", tag = "service",
    responses(
        (status = 200, description = "Prometheus text exposition (format 0.0.4).",
            content_type = "text/plain; version=0.0.4; charset=utf-8", body = String),
        (status = 401, response = Unauthorized), (status = 403, response = Forbidden),
        (status = 421, response = Misdirected)))]
pub(super) async fn metrics(State(service): Shared) -> Response {
    (
        [(
            header::CONTENT_TYPE,
            "text/plain; version=0.0.4; charset=utf-8",
        )],
        service.metrics_text(),
    )
        .into_response()
}

/// Service health and load (open without a token).
#[utoipa::path(get, path = "/v1/health", tag = "service",
    responses((status = 200,
            description = "Health and load.",
            body = crate::api::Health), (status = 421, response = Misdirected)))]
pub(super) async fn health(State(service): Shared, caller: Caller) -> HttpResult {
    json(
        StatusCode::OK,
        run(&service, &caller, Command::Health).await?,
    )
}

/// List sessions (sorted by name; with tokens, those of the caller's token).
#[utoipa::path(get, path = "/v1/sessions", tag = "sessions",
    responses((status = 200,
            description = "The sessions.",
            body = crate::api::SessionList), (status = 401, response = Unauthorized), (status = 421, response = Misdirected), (status = 503, response = Unavailable)))]
pub(super) async fn list_sessions(State(service): Shared, caller: Caller) -> HttpResult {
    json(
        StatusCode::OK,
        run(&service, &caller, Command::ListSessions).await?,
    )
}

/// Create a session.
#[utoipa::path(post, path = "/v1/sessions", tag = "sessions",
    request_body = CreateSession,
    responses((status = 201,
            description = "Created.",
            body = crate::api::wire::SessionInfo), (status = 400, response = BadRequest), (status = 401, response = Unauthorized), (status = 403, response = Forbidden), (status = 409, response = Conflict), (status = 413, response = PayloadTooLarge), (status = 415, response = UnsupportedMediaType), (status = 421, response = Misdirected), (status = 503, response = Unavailable)))]
pub(super) async fn create_session(
    State(service): Shared,
    caller: Caller,
    body: Result<Bytes, BytesRejection>,
) -> HttpResult {
    let request: CreateSession = parse_json(&body.map_err(body_error)?)?;
    let command = Command::CreateSession(request);
    json(StatusCode::CREATED, run(&service, &caller, command).await?)
}

/// A session's state and statistics.
#[utoipa::path(get, path = "/v1/sessions/{session}", tag = "sessions", params(SessionPath),
    responses((status = 200,
            description = "The session's statistics.",
            body = crate::api::wire::SessionStats), (status = 401, response = Unauthorized), (status = 404, response = NotFound), (status = 421, response = Misdirected), (status = 503, response = Unavailable)))]
pub(super) async fn stats(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
) -> HttpResult {
    json(
        StatusCode::OK,
        run(&service, &caller, Command::GetStats(GetStats { session })).await?,
    )
}

/// Delete a session (its files too).
#[utoipa::path(delete, path = "/v1/sessions/{session}", tag = "sessions", params(SessionPath),
    responses((status = 200,
            description = "Deleted.",
            body = crate::api::Deleted), (status = 401, response = Unauthorized), (status = 403, response = Forbidden), (status = 404, response = NotFound), (status = 421, response = Misdirected), (status = 503, response = Unavailable)))]
pub(super) async fn delete_session(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
) -> HttpResult {
    json(
        StatusCode::OK,
        run(
            &service,
            &caller,
            Command::DeleteSession(DeleteSession { session }),
        )
        .await?,
    )
}

#[derive(Deserialize, Default, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
struct WaitParam {
    /// `true`: answer once the estimate reflects the request (bounded by `wait_timeout_ms`).
    #[serde(default)]
    wait: bool,
}

#[derive(Deserialize, Default, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
struct OptimizeParams {
    /// `true`: answer once the solve is over (bounded by `wait_timeout_ms`).
    #[serde(default)]
    wait: bool,
    /// Solve only once this producer's batches up to `after_seq` are applied, whichever
    /// transport they travelled on (at most `after_timeout_ms`, default 10000: 503
    /// `after_timeout`).
    #[serde(default)]
    after_producer: Option<String>,
    #[serde(default)]
    after_seq: Option<u64>,
    #[serde(default)]
    after_timeout_ms: Option<u64>,
}

/// Apply a batch: validated whole, applied whole or not at all, journalled before it is
/// acknowledged. With `wait`, answers once the estimate reflects it (`solved`).
#[utoipa::path(post, path = "/v1/sessions/{session}/batches", tag = "updates", params(SessionPath, WaitParam),
    request_body = Batch,
    responses((status = 200,
            description = "Accepted; `solved` only with `wait`.",
            body = crate::api::Accepted), (status = 400, response = BadRequest), (status = 401, response = Unauthorized), (status = 403, response = Forbidden), (status = 404, response = NotFound), (status = 409, response = Conflict), (status = 413, response = PayloadTooLarge), (status = 415, response = UnsupportedMediaType), (status = 421, response = Misdirected), (status = 422, response = Unprocessable), (status = 429, response = TooMany), (status = 503, response = Unavailable)))]
pub(super) async fn apply_batch(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
    raw: RawQuery,
    body: Result<Bytes, BytesRejection>,
) -> HttpResult {
    let WaitParam { wait } = query(raw)?;
    let max_items = service.limits().max_batch_items;
    let batch: Batch = parse_json_within(&body.map_err(body_error)?, max_items)?;
    json(
        StatusCode::OK,
        run(
            &service,
            &caller,
            Command::ApplyBatch(ApplyBatch {
                session,
                batch,
                wait,
            }),
        )
        .await?,
    )
}

/// Fusion messages for a `sliding_window` session (IMU samples, keyframes, relative poses,
/// priors).
#[utoipa::path(post, path = "/v1/sessions/{session}/fusion", tag = "updates", params(SessionPath),
    request_body = FusionBatch,
    responses((status = 200,
            description = "Applied.",
            body = crate::api::fusion::FusionAck), (status = 400, response = BadRequest), (status = 401, response = Unauthorized), (status = 403, response = Forbidden), (status = 404, response = NotFound), (status = 409, response = Conflict), (status = 413, response = PayloadTooLarge), (status = 415, response = UnsupportedMediaType), (status = 421, response = Misdirected), (status = 422, response = Unprocessable), (status = 503, response = Unavailable)))]
pub(super) async fn fusion(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
    body: Result<Bytes, BytesRejection>,
) -> HttpResult {
    let max_items = service.limits().max_batch_items;
    let batch: FusionBatch = parse_json_within(&body.map_err(body_error)?, max_items)?;
    let messages = batch.messages;
    json(
        StatusCode::OK,
        run(
            &service,
            &caller,
            Command::Fusion(Fusion { session, messages }),
        )
        .await?,
    )
}

/// Solve now, whatever the policy: 202 at once, or with `wait` 200 when the solve is over
/// (with the session's `stats`).
#[utoipa::path(post, path = "/v1/sessions/{session}/optimize", tag = "updates", params(SessionPath, OptimizeParams),
    responses(
        (status = 200, description = "With `wait`: the solve finished.", body = crate::api::Optimizing),
        (status = 202, description = "The solve was started or scheduled.", body = crate::api::Optimizing),
        (status = 400, response = BadRequest), (status = 401, response = Unauthorized), (status = 403, response = Forbidden), (status = 404, response = NotFound), (status = 409, response = Conflict), (status = 421, response = Misdirected), (status = 422, response = Unprocessable), (status = 503, response = Unavailable)))]
pub(super) async fn optimize(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
    raw: RawQuery,
) -> HttpResult {
    let OptimizeParams {
        wait,
        after_producer,
        after_seq,
        after_timeout_ms,
    } = query(raw)?;
    let status = if wait {
        StatusCode::OK
    } else {
        StatusCode::ACCEPTED
    };
    json(
        status,
        run(
            &service,
            &caller,
            Command::Optimize(Optimize {
                session,
                wait,
                after: AfterFields {
                    after_producer,
                    after_seq,
                    after_timeout_ms,
                },
            }),
        )
        .await?,
    )
}

/// Change when the session re-optimises by itself.
#[utoipa::path(put, path = "/v1/sessions/{session}/auto_optimize", tag = "updates", params(SessionPath),
    request_body = AutoOptimize,
    responses((status = 200,
            description = "The new policy.",
            body = crate::api::AutoOptimizeSet), (status = 400, response = BadRequest), (status = 401, response = Unauthorized), (status = 403, response = Forbidden), (status = 404, response = NotFound), (status = 409, response = Conflict), (status = 413, response = PayloadTooLarge), (status = 415, response = UnsupportedMediaType), (status = 421, response = Misdirected), (status = 503, response = Unavailable)))]
pub(super) async fn set_auto_optimize(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
    body: Result<Bytes, BytesRejection>,
) -> HttpResult {
    let auto_optimize: AutoOptimize = parse_json(&body.map_err(body_error)?)?;
    json(
        StatusCode::OK,
        run(
            &service,
            &caller,
            Command::SetAutoOptimize(SetAutoOptimize {
                session,
                auto_optimize,
            }),
        )
        .await?,
    )
}

/// Declare more user-defined factor types in a running graph session (all or none).
#[utoipa::path(post, path = "/v1/sessions/{session}/factor_types", tag = "updates", params(SessionPath),
    request_body = super::openapi::FactorTypesBody,
    responses((status = 200,
            description = "The session, with every declared factor type's name.",
            body = crate::api::wire::SessionInfo), (status = 400, response = BadRequest), (status = 401, response = Unauthorized), (status = 403, response = Forbidden), (status = 404, response = NotFound), (status = 409, response = Conflict), (status = 413, response = PayloadTooLarge), (status = 415, response = UnsupportedMediaType), (status = 421, response = Misdirected), (status = 503, response = Unavailable)))]
pub(super) async fn define_factor_types(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
    body: Result<Bytes, BytesRejection>,
) -> HttpResult {
    let body: super::openapi::FactorTypesBody = parse_json(&body.map_err(body_error)?)?;
    json(
        StatusCode::OK,
        run(
            &service,
            &caller,
            Command::DefineFactorTypes(DefineFactorTypes {
                session,
                factor_types: body.factor_types,
            }),
        )
        .await?,
    )
}

/// Read the estimate: every variable, those changed after `since`, or a key range; with
/// `format=tum|kitti|g2o|ply` as that file (text; a window session's trajectory).
#[utoipa::path(get, path = "/v1/sessions/{session}/estimate", tag = "reads", params(SessionPath, EstimateQuery),
    responses((status = 200,
            description = "The estimate (JSON), or with `format` a TUM, KITTI, g2o or PLY file as text.",
            content((crate::api::wire::Estimate = "application/json"), (String = "text/plain; charset=utf-8"))), (status = 400, response = BadRequest), (status = 401, response = Unauthorized), (status = 404, response = NotFound), (status = 421, response = Misdirected), (status = 503, response = Unavailable)))]
pub(super) async fn estimate(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
    raw: RawQuery,
) -> HttpResult {
    let estimate: EstimateQuery = query(raw)?;
    match run(&service, &caller, Command::get_estimate(session, estimate)).await? {
        Reply::Export(file) => Ok((
            [
                (header::CONTENT_TYPE, Export::MEDIA_TYPE.to_string()),
                (
                    header::CONTENT_DISPOSITION,
                    format!("inline; filename=\"{}\"", file.file_name),
                ),
            ],
            file.body,
        )
            .into_response()),
        reply => json(StatusCode::OK, reply),
    }
}

/// What the web view draws: positions, initial guesses, pose-to-pose edges.
#[utoipa::path(get, path = "/v1/sessions/{session}/graph", tag = "reads", params(SessionPath),
    responses((status = 200,
            description = "The graph.",
            body = crate::api::wire::Graph), (status = 401, response = Unauthorized), (status = 404, response = NotFound), (status = 421, response = Misdirected), (status = 503, response = Unavailable)))]
pub(super) async fn graph(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
) -> HttpResult {
    json(
        StatusCode::OK,
        run(&service, &caller, Command::GetGraph(GetGraph { session })).await?,
    )
}

/// The session's history: a timeline of its solves (χ², solve time, update latency), its last
/// events as streamed, rejected inputs and `last_error` (kept bounded in memory; the web view
/// reads it on load).
#[utoipa::path(get, path = "/v1/sessions/{session}/history", tag = "reads", params(SessionPath),
    responses((status = 200,
            description = "The history.",
            body = crate::api::history::SessionHistory), (status = 401, response = Unauthorized), (status = 404, response = NotFound), (status = 421, response = Misdirected), (status = 503, response = Unavailable)))]
pub(super) async fn history(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
) -> HttpResult {
    json(
        StatusCode::OK,
        run(
            &service,
            &caller,
            Command::GetHistory(GetHistory { session }),
        )
        .await?,
    )
}

/// `?keys=3,17&joint=true`: keys as one comma-separated list.
#[derive(Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
struct MarginalsParams {
    /// Variable keys, comma-separated (`3,17`).
    keys: String,
    /// Also return the joint covariance of all of them.
    #[serde(default)]
    joint: bool,
}

/// Where a producer's batches stand: every batch up to `accepted_through` is applied (a
/// reconnecting producer resends only what follows).
#[utoipa::path(get, path = "/v1/sessions/{session}/producers/{producer}", tag = "reads", params(SessionPath, super::openapi::ProducerPath),
    responses((status = 200,
            description = "The producer's progress (0 for one never seen).",
            body = crate::api::wire::ProducerStatus), (status = 401, response = Unauthorized), (status = 404, response = NotFound), (status = 421, response = Misdirected), (status = 503, response = Unavailable)))]
pub(super) async fn producer_status(
    State(service): Shared,
    caller: Caller,
    Path((session, producer)): Path<(String, String)>,
) -> HttpResult {
    json(
        StatusCode::OK,
        run(
            &service,
            &caller,
            Command::ProducerStatus(ProducerQuery { session, producer }),
        )
        .await?,
    )
}

/// Every producer that sent the session a numbered batch, by id, with where its batches stand.
#[utoipa::path(get, path = "/v1/sessions/{session}/producers", tag = "reads", params(SessionPath),
    responses((status = 200, description = "The producers.", body = crate::api::ProducerList),
        (status = 401, response = Unauthorized), (status = 404, response = NotFound), (status = 421, response = Misdirected), (status = 503, response = Unavailable)))]
pub(super) async fn list_producers(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
) -> HttpResult {
    let command = Command::ListProducers(ListProducers { session });
    json(StatusCode::OK, run(&service, &caller, command).await?)
}

/// A session's robots (created with `robots`): their frames, components, held and rejected
/// closures, and merges.
#[utoipa::path(get, path = "/v1/sessions/{session}/robots", tag = "reads", params(SessionPath),
    responses((status = 200, description = "The robots.", body = crate::api::robots::RobotsReport),
        (status = 400, response = BadRequest), (status = 401, response = Unauthorized), (status = 404, response = NotFound), (status = 421, response = Misdirected), (status = 503, response = Unavailable)))]
pub(super) async fn list_robots(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
) -> HttpResult {
    let command = Command::ListRobots(ListRobots { session });
    json(StatusCode::OK, run(&service, &caller, command).await?)
}

/// A session's possibly wrong loop closures (marked `"outlier": "auto"`, or every loop closure
/// of a session created with `"outliers": "auto"`): accepted, pending and rejected.
#[utoipa::path(get, path = "/v1/sessions/{session}/outliers", tag = "reads", params(SessionPath),
    responses((status = 200, description = "The candidates and the decisions.", body = crate::api::outliers::OutliersReport),
        (status = 400, response = BadRequest), (status = 401, response = Unauthorized), (status = 404, response = NotFound), (status = 421, response = Misdirected), (status = 503, response = Unavailable)))]
pub(super) async fn list_outliers(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
) -> HttpResult {
    let command = Command::ListOutliers(ListOutliers { session });
    json(StatusCode::OK, run(&service, &caller, command).await?)
}

/// Marginal covariances of `keys` at the current estimate (and their joint covariance).
#[utoipa::path(get, path = "/v1/sessions/{session}/marginals", tag = "reads", params(SessionPath, MarginalsParams),
    responses((status = 200,
            description = "The covariances.",
            body = crate::api::wire::Marginals), (status = 400, response = BadRequest), (status = 401, response = Unauthorized), (status = 404, response = NotFound), (status = 409, response = Conflict), (status = 413, response = PayloadTooLarge), (status = 421, response = Misdirected), (status = 422, response = Unprocessable), (status = 503, response = Unavailable)))]
pub(super) async fn marginals(
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
    json(
        StatusCode::OK,
        run(
            &service,
            &caller,
            Command::GetMarginals(GetMarginals {
                session,
                keys,
                joint,
            }),
        )
        .await?,
    )
}

/// The summary of the session's last solve (404 `no_summary` before the first).
#[utoipa::path(get, path = "/v1/sessions/{session}/summary", tag = "reads", params(SessionPath),
    responses((status = 200,
            description = "The last solve's summary.",
            body = crate::solver::Summary), (status = 401, response = Unauthorized), (status = 404, response = NotFound), (status = 421, response = Misdirected), (status = 503, response = Unavailable)))]
pub(super) async fn summary(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
) -> HttpResult {
    let command = Command::GetStats(GetStats { session });
    let Reply::Stats(stats) = run(&service, &caller, command).await? else {
        unreachable!("GetStats answers with Stats");
    };
    match stats.last_summary {
        Some(summary) => Ok(Json(summary).into_response()),
        None => Err(ServiceError::new(
            ErrorKind::NotFound,
            "no_summary",
            "this session has not been solved yet",
        )
        .into()),
    }
}

/// Stop the running solve after its current iteration.
#[utoipa::path(post, path = "/v1/sessions/{session}/cancel", tag = "updates", params(SessionPath),
    responses((status = 200,
            description = "Whether a solve was running.",
            body = crate::api::Cancelled), (status = 401, response = Unauthorized), (status = 403, response = Forbidden), (status = 404, response = NotFound), (status = 421, response = Misdirected), (status = 503, response = Unavailable)))]
pub(super) async fn cancel(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
) -> HttpResult {
    json(
        StatusCode::OK,
        run(&service, &caller, Command::Cancel(Cancel { session })).await?,
    )
}

/// Optimise a whole graph file (g2o, TORO, BAL text in the body) in one shot.
#[utoipa::path(post, path = "/v1/jobs", tag = "jobs", params(super::openapi::JobQuery),
    request_body(content = String, content_type = "text/plain", description = "The graph file."),
    responses(
        (status = 200, description = "The summary and estimate as JSON, or the optimised graph as text with `output`.",
            content((super::openapi::JobResult = "application/json"), (String = "text/plain"))),
        (status = 400, response = BadRequest), (status = 401, response = Unauthorized), (status = 403, response = Forbidden), (status = 413, response = PayloadTooLarge), (status = 421, response = Misdirected), (status = 422, response = Unprocessable), (status = 503, response = Unavailable)))]
pub(super) async fn job(
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
