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
