//! The one error type of the command API. Every transport renders it the same way: HTTP as a
//! status code and `{"error": {"code", "message", "field"?}}`, zenoh as an error reply with the
//! same body plus the status.

use serde::{Deserialize, Serialize};

/// The JSON body of an error.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
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

#[derive(Clone, Debug, thiserror::Error, PartialEq)]
#[error("{}", body.message)]
pub struct ServiceError {
    pub body: ErrorBody,
}

impl ServiceError {
    pub fn new(status: u16, code: &str, message: impl Into<String>) -> Self {
        Self {
            body: ErrorBody {
                code: code.into(),
                message: message.into(),
                field: None,
                status,
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
        Self::new(400, code, message).at(field)
    }

    /// 422: well-formed, but invalid against the session's current contents.
    pub fn invalid(code: &str, field: impl Into<String>, message: impl Into<String>) -> Self {
        Self::new(422, code, message).at(field)
    }

    pub fn not_found(what: &str, name: &str) -> Self {
        Self::new(
            404,
            &format!("unknown_{what}"),
            format!("no {what} named `{name}`"),
        )
    }

    pub fn conflict(code: &str, message: impl Into<String>) -> Self {
        Self::new(409, code, message)
    }

    /// 429: this session has too much waiting; retry later.
    pub fn too_many(message: impl Into<String>, retry_after: u64) -> Self {
        let mut e = Self::new(429, "too_many_pending", message);
        e.body.retry_after = Some(retry_after);
        e
    }

    /// 503: the service as a whole is at capacity or shutting down.
    pub fn unavailable(code: &str, message: impl Into<String>, retry_after: u64) -> Self {
        let mut e = Self::new(503, code, message);
        e.body.retry_after = Some(retry_after);
        e
    }

    pub fn internal(message: impl Into<String>) -> Self {
        Self::new(500, "internal", message)
    }

    pub fn status(&self) -> u16 {
        self.body.status
    }
}

/// Parses a JSON request body (an object), naming the offending field on failure.
pub fn parse_json<T: serde::de::DeserializeOwned>(bytes: &[u8]) -> Result<T, ServiceError> {
    // serde would also fill a struct from an array by position; the API only speaks objects.
    match bytes.iter().find(|b| !b.is_ascii_whitespace()) {
        Some(b'{') => {}
        Some(_) => {
            return Err(ServiceError::new(
                400,
                "malformed_json",
                "the body must be a JSON object",
            ))
        }
        None => {
            return Err(ServiceError::new(
                400,
                "malformed_json",
                "the body is empty",
            ))
        }
    }
    let de = &mut serde_json::Deserializer::from_slice(bytes);
    serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        let code = if inner.is_syntax() || inner.is_eof() {
            "malformed_json"
        } else {
            "invalid_field"
        };
        let err = ServiceError::new(400, code, format!("invalid JSON body: {inner}"));
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
    use crate::session::wire_list::{check_shape, decode_within, ShapeError};
    match check_shape(bytes, max_items) {
        Ok(()) => {}
        Err(e @ ShapeError::TooManyItems { .. }) => {
            return Err(ServiceError::new(413, "batch_too_large", e.to_string()).at("batch"))
        }
        Err(e @ ShapeError::TooManyNumbers) => {
            return Err(ServiceError::new(413, "list_too_long", e.to_string()).at("body"))
        }
    }
    let mut beyond = None;
    let decoded = decode_within(max_items, || {
        parse_json::<T>(bytes).inspect_err(|e| beyond = e.body.field.clone())
    });
    decoded.unwrap_or_else(|exceeded| {
        let error = ServiceError::new(
            413,
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
