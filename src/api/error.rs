//! The one error type of the command API. Layers below the transports say *what kind* of failure
//! it is ([`ErrorKind`]) with a stable code and the field at fault; [`ErrorKind::status`] is the
//! one place that maps a kind to an HTTP status. Every transport renders it the same way: HTTP as
//! that status and `{"error": {"code", "message", "field"?}}`, zenoh as an error reply with the
//! same body plus the status.

use serde::{Deserialize, Serialize};

/// The JSON body of an error.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
pub struct ErrorBody {
    /// Stable machine-readable code, e.g. `unknown_variable`.
    pub code: String,
    pub message: String,
    /// Where in the request the problem is, e.g. `factors[3].information`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub field: Option<String>,
    /// HTTP-equivalent status (also on zenoh replies).
    pub status: u16,
    /// Seconds to wait before retrying (back-pressure).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub retry_after: Option<u64>,
}

/// What kind of failure an error is, independent of any transport.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ErrorKind {
    /// The request is malformed or names something impossible.
    BadRequest,
    /// No or a wrong credential.
    Unauthorized,
    /// The caller may not do this (or a cross-site request).
    Forbidden,
    NotFound,
    MethodNotAllowed,
    /// The request contradicts the state (an existing name, a damaged journal).
    Conflict,
    /// The request (its body) did not arrive in time.
    RequestTimeout,
    /// The request or the work it asks for is bigger than the limits allow.
    TooLarge,
    UriTooLong,
    UnsupportedMediaType,
    /// The request was addressed to another host.
    Misdirected,
    /// Well-formed, but invalid against the session's current contents (or unsolvable).
    Invalid,
    /// This session or caller has too much waiting: retry later.
    TooMany,
    HeadersTooLarge,
    Internal,
    /// The service as a whole is at capacity or shutting down.
    Unavailable,
}

impl ErrorKind {
    /// The HTTP status of this kind (zenoh replies carry the same number).
    pub const fn status(self) -> u16 {
        match self {
            Self::BadRequest => 400,
            Self::Unauthorized => 401,
            Self::Forbidden => 403,
            Self::NotFound => 404,
            Self::MethodNotAllowed => 405,
            Self::Conflict => 409,
            Self::RequestTimeout => 408,
            Self::TooLarge => 413,
            Self::UriTooLong => 414,
            Self::UnsupportedMediaType => 415,
            Self::Misdirected => 421,
            Self::Invalid => 422,
            Self::TooMany => 429,
            Self::HeadersTooLarge => 431,
            Self::Internal => 500,
            Self::Unavailable => 503,
        }
    }

    /// The kind of an HTTP status a transport's own machinery produced (a rejection by the HTTP
    /// library, say); statuses without a kind of their own count as bad requests or, from 500
    /// on, as internal errors.
    pub fn from_status(status: u16) -> Self {
        const ALL: [ErrorKind; 16] = [
            ErrorKind::BadRequest,
            ErrorKind::Unauthorized,
            ErrorKind::Forbidden,
            ErrorKind::NotFound,
            ErrorKind::MethodNotAllowed,
            ErrorKind::Conflict,
            ErrorKind::RequestTimeout,
            ErrorKind::TooLarge,
            ErrorKind::UriTooLong,
            ErrorKind::UnsupportedMediaType,
            ErrorKind::Misdirected,
            ErrorKind::Invalid,
            ErrorKind::TooMany,
            ErrorKind::HeadersTooLarge,
            ErrorKind::Internal,
            ErrorKind::Unavailable,
        ];
        match ALL.into_iter().find(|k| k.status() == status) {
            Some(kind) => kind,
            None if status >= 500 => Self::Internal,
            None => Self::BadRequest,
        }
    }
}

#[derive(Clone, Debug, thiserror::Error, PartialEq)]
#[error("{}", body.message)]
pub struct ServiceError {
    pub kind: ErrorKind,
    pub body: ErrorBody,
}

impl ServiceError {
    pub fn new(kind: ErrorKind, code: &str, message: impl Into<String>) -> Self {
        Self {
            kind,
            body: ErrorBody {
                code: code.into(),
                message: message.into(),
                field: None,
                status: kind.status(),
                retry_after: None,
            },
        }
    }

    pub fn at(mut self, field: impl Into<String>) -> Self {
        self.body.field = Some(field.into());
        self
    }

    /// 400: the request is malformed or names something impossible.
    pub fn bad_request(code: &str, field: impl Into<String>, message: impl Into<String>) -> Self {
        Self::new(ErrorKind::BadRequest, code, message).at(field)
    }

    /// 422: well-formed, but invalid against the session's current contents.
    pub fn invalid(code: &str, field: impl Into<String>, message: impl Into<String>) -> Self {
        Self::new(ErrorKind::Invalid, code, message).at(field)
    }

    pub fn not_found(what: &str, name: &str) -> Self {
        Self::new(
            ErrorKind::NotFound,
            &format!("unknown_{what}"),
            format!("no {what} named `{name}`"),
        )
    }

    pub fn conflict(code: &str, message: impl Into<String>) -> Self {
        Self::new(ErrorKind::Conflict, code, message)
    }

    /// 429: this session has too much waiting; retry later.
    pub fn too_many(message: impl Into<String>, retry_after: u64) -> Self {
        let mut e = Self::new(ErrorKind::TooMany, "too_many_pending", message);
        e.body.retry_after = Some(retry_after);
        e
    }

    /// 503: the service as a whole is at capacity or shutting down.
    pub fn unavailable(code: &str, message: impl Into<String>, retry_after: u64) -> Self {
        let mut e = Self::new(ErrorKind::Unavailable, code, message);
        e.body.retry_after = Some(retry_after);
        e
    }

    pub fn internal(message: impl Into<String>) -> Self {
        Self::new(ErrorKind::Internal, "internal", message)
    }

    /// 413: the request or the work it asks for exceeds a limit.
    pub fn too_large(code: &str, message: impl Into<String>) -> Self {
        Self::new(ErrorKind::TooLarge, code, message)
    }

    pub fn status(&self) -> u16 {
        self.kind.status()
    }
}

/// Parses a JSON request body (an object), naming the offending field on failure.
///
/// A valid body is decoded once, straight; only one that fails is decoded again through
/// `serde_path_to_error` to name the field (tracking the path of every value costs about a
/// fifth of the decoding, measured on 1000-factor batches).
pub fn parse_json<T: serde::de::DeserializeOwned>(bytes: &[u8]) -> Result<T, ServiceError> {
    require_object(bytes)?;
    match serde_json::from_slice(bytes) {
        Ok(value) => Ok(value),
        Err(_) => parse_json_located(bytes),
    }
}

/// The body starts with `{` (serde would also fill a struct from an array by position; the API
/// only speaks objects).
fn require_object(bytes: &[u8]) -> Result<(), ServiceError> {
    match bytes.iter().find(|b| !b.is_ascii_whitespace()) {
        Some(b'{') => {}
        Some(_) => {
            return Err(ServiceError::new(
                ErrorKind::BadRequest,
                "malformed_json",
                "the body must be a JSON object",
            ))
        }
        None => {
            return Err(ServiceError::new(
                ErrorKind::BadRequest,
                "malformed_json",
                "the body is empty",
            ))
        }
    }
    Ok(())
}

/// Decodes `bytes` tracking the path of every value, so an error names its field.
fn parse_json_located<T: serde::de::DeserializeOwned>(bytes: &[u8]) -> Result<T, ServiceError> {
    let de = &mut serde_json::Deserializer::from_slice(bytes);
    serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        let code = if inner.is_syntax() || inner.is_eof() {
            "malformed_json"
        } else {
            "invalid_field"
        };
        let err = ServiceError::new(
            ErrorKind::BadRequest,
            code,
            format!("invalid JSON body: {inner}"),
        );
        if path == "." {
            err
        } else {
            err.at(path)
        }
    })
}

/// Parses a JSON request body whose item lists (see `session::wire_list`) hold at most
/// `max_items` items in all: 413 `batch_too_large` at the first item beyond, before the rest of
/// the body is decoded.
pub fn parse_json_within<T: serde::de::DeserializeOwned>(
    bytes: &[u8],
    max_items: usize,
) -> Result<T, ServiceError> {
    use crate::api::wire_list::{check_shape, decode_within, ShapeError};
    match check_shape(bytes, max_items) {
        Ok(()) => {}
        Err(e @ ShapeError::TooManyItems { .. }) => {
            return Err(ServiceError::too_large("batch_too_large", e.to_string()).at("batch"))
        }
        Err(e @ ShapeError::TooManyNumbers) => {
            return Err(ServiceError::too_large("list_too_long", e.to_string()).at("body"))
        }
    }
    require_object(bytes)?;
    // The common case first, as `parse_json` does; the budget starts afresh for the second
    // decoding of a failing body.
    if let Ok(Ok(value)) = decode_within(max_items, || serde_json::from_slice::<T>(bytes)) {
        return Ok(value);
    }
    let mut beyond = None;
    let decoded = decode_within(max_items, || {
        parse_json_located::<T>(bytes).inspect_err(|e| beyond = e.body.field.clone())
    });
    decoded.unwrap_or_else(|exceeded| {
        let error = ServiceError::too_large(
            "batch_too_large",
            format!(
                "the request has more than {} items (variables, factors, removals, fixes, \
                 guesses, messages; limits.max_batch_items): split it",
                exceeded.limit
            ),
        );
        Err(error.at(beyond.unwrap_or_else(|| "batch".into())))
    })
}

/// Parses query parameters (`a=1&b=2`; zenoh selectors separate them with `;`), naming the
/// offending parameter on failure.
pub fn parse_query<T: serde::de::DeserializeOwned>(query: &str) -> Result<T, ServiceError> {
    let query = query.replace(';', "&");
    let de = serde_urlencoded::Deserializer::new(form_urlencoded::parse(query.as_bytes()));
    serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        let message = e.into_inner().to_string();
        // An unknown parameter is named in the message, not the path.
        let field = match message.split('`').nth(1) {
            Some(name) if path == "." => name.to_string(),
            _ => path,
        };
        ServiceError::bad_request(
            "invalid_query",
            field,
            format!("invalid query parameter: {message}"),
        )
    })
}

#[cfg(test)]
mod tests {
    use super::ErrorKind;

    #[test]
    fn every_kind_has_its_own_status_and_comes_back_from_it() {
        let kinds = [
            400, 401, 403, 404, 405, 409, 413, 414, 415, 421, 422, 429, 431, 500, 503,
        ]
        .map(ErrorKind::from_status);
        for (i, kind) in kinds.iter().enumerate() {
            assert_eq!(ErrorKind::from_status(kind.status()), *kind);
            assert!(kinds[..i].iter().all(|k| k.status() != kind.status()));
        }
        assert_eq!(ErrorKind::from_status(418), ErrorKind::BadRequest);
        assert_eq!(ErrorKind::from_status(502), ErrorKind::Internal);
    }
}
