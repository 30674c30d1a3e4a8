//! The JSON error body, for our errors and for those axum answers itself.

use axum::extract::rejection::BytesRejection;
use axum::extract::RawQuery;
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;

use crate::api::ErrorKind;
use crate::service::{parse_query, ServiceError};

/// Errors axum's own extractors answer in plain text (a path segment that is not UTF-8, a
/// WebSocket request without its upgrade headers) become our JSON error body, so every API
/// error has the same shape.
pub(super) async fn json_errors(
    request: axum::extract::Request,
    next: axum::middleware::Next,
) -> Response {
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
    HttpError(ServiceError::new(
        ErrorKind::from_status(status.as_u16()),
        code,
        message,
    ))
    .into_response()
}

/// An error as an HTTP response.
pub struct HttpError(pub(super) ServiceError);

impl From<ServiceError> for HttpError {
    fn from(e: ServiceError) -> Self {
        Self(e)
    }
}

impl IntoResponse for HttpError {
    fn into_response(self) -> Response {
        let body = self.0.body;
        crate::runtime::metrics::count_rejection(&body);
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

pub(super) type HttpResult = Result<Response, HttpError>;

pub(super) fn body_error(rejection: BytesRejection) -> HttpError {
    // A body cut off by the listener's limits (too slow, or too large without a credential).
    if let Some(refusal) = super::body_limits::BodyRefusal::find(&rejection) {
        return HttpError(refusal.to_service_error());
    }
    let status = rejection.status();
    let code = if status == StatusCode::PAYLOAD_TOO_LARGE {
        "body_too_large"
    } else {
        "unreadable_body"
    };
    HttpError(
        ServiceError::new(
            ErrorKind::from_status(status.as_u16()),
            code,
            rejection.body_text(),
        )
        .at("body"),
    )
}

pub(super) fn query<T: serde::de::DeserializeOwned>(raw: RawQuery) -> Result<T, HttpError> {
    Ok(parse_query(raw.0.as_deref().unwrap_or(""))?)
}

pub(super) async fn not_found() -> HttpError {
    HttpError(ServiceError::new(
        ErrorKind::NotFound,
        "no_route",
        "no such route (the API is under /v1/)",
    ))
}

pub(super) async fn method_not_allowed() -> HttpError {
    HttpError(ServiceError::new(
        ErrorKind::MethodNotAllowed,
        "method_not_allowed",
        "this route does not take that method",
    ))
}
