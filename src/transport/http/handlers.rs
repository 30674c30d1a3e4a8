//! One handler per REST route: decode the request, run its command as the caller, render the reply.

use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::rejection::BytesRejection;
use axum::extract::{Path, RawQuery, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::Deserialize;

use crate::api::fusion::FusionBatch;
use crate::api::wire::{AutoOptimize, Batch, CreateSession, EstimateQuery};
use crate::api::ErrorKind;
use crate::service::jobs::{JobAnswer, JobParams};
use crate::service::{parse_json, parse_json_within, Command, Reply, Service, ServiceError};

pub(super) type Shared = State<Arc<Service>>;
use super::errors::{body_error, query, HttpResult};

/// The request's caller, left by the auth layer (see `router`).
pub(super) type Caller = axum::Extension<crate::service::Caller>;

pub(super) async fn run(
    service: &Service,
    caller: &Caller,
    command: Command,
    status: StatusCode,
) -> HttpResult {
    let reply = service.execute_as(&caller.0, command).await?;
    Ok((status, Json(reply)).into_response())
}

/// Prometheus text exposition.
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

pub(super) async fn health(State(service): Shared, caller: Caller) -> HttpResult {
    run(&service, &caller, Command::Health, StatusCode::OK).await
}

pub(super) async fn list_sessions(State(service): Shared, caller: Caller) -> HttpResult {
    run(&service, &caller, Command::ListSessions, StatusCode::OK).await
}

pub(super) async fn create_session(
    State(service): Shared,
    caller: Caller,
    body: Result<Bytes, BytesRejection>,
) -> HttpResult {
    let request: CreateSession = parse_json(&body.map_err(body_error)?)?;
    let command = Command::CreateSession(request);
    run(&service, &caller, command, StatusCode::CREATED).await
}

pub(super) async fn stats(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
) -> HttpResult {
    run(
        &service,
        &caller,
        Command::GetStats { session },
        StatusCode::OK,
    )
    .await
}

pub(super) async fn delete_session(
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

pub(super) async fn fusion(
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

pub(super) async fn optimize(
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

pub(super) async fn set_auto_optimize(
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

pub(super) async fn estimate(
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

pub(super) async fn graph(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
) -> HttpResult {
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

pub(super) async fn summary(
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
        None => Err(ServiceError::new(
            ErrorKind::NotFound,
            "no_summary",
            "this session has not been solved yet",
        )
        .into()),
    }
}

pub(super) async fn cancel(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
) -> HttpResult {
    run(
        &service,
        &caller,
        Command::Cancel { session },
        StatusCode::OK,
    )
    .await
}

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
