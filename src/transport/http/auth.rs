//! Bearer-token authentication for HTTP, and session ownership.
//!
//! Tokens come from a file (`auth.tokens_file`, one `label token` or bare `token` per line, `#`
//! comments) and/or `FACTORD_TOKENS` (comma-separated). They are required automatically when
//! HTTP listens beyond loopback. With tokens in force every route but `GET /v1/health`, the web
//! pages and the API's description (`/v1/openapi.json`, `/v1/docs`: not secret, like the pages'
//! own code) needs `Authorization: Bearer <token>` (401 otherwise), or on reads (GET and HEAD,
//! not WebSocket upgrades) the web view's cookie set by `POST /v1/login` (see `login`): a
//! cross-site form cannot change anything with it. A session belongs to the
//! label of the token that created it: to any other caller it does not exist (404), nor is it
//! listed or counted (see `service::caller`). Sessions created over an unauthenticated zenoh or
//! before tokens were configured belong to nobody and are reachable with any valid token.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use axum::extract::{Request, State};
use axum::http::{header, HeaderValue, Method};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::admission::ConnectionContext;
use crate::api::ErrorKind;
use crate::service::{Caller, ServiceError};

#[derive(Debug, Default)]
pub struct Tokens {
    /// token → label
    by_token: HashMap<String, Arc<str>>,
}

#[derive(Debug, thiserror::Error)]
pub enum TokensError {
    #[error("tokens file {file}: {message}")]
    File { file: PathBuf, message: String },
}

impl Tokens {
    /// From a file's text: `label token` or `token` per line.
    pub fn parse(text: &str, file: &Path) -> Result<Self, TokensError> {
        let mut tokens = Self::default();
        for (n, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let (label, token) = match line.split_whitespace().collect::<Vec<_>>()[..] {
                [token] => (format!("{}:{}", file.display(), n + 1), token),
                [label, token] => (label.to_string(), token),
                _ => {
                    return Err(TokensError::File {
                        file: file.into(),
                        message: format!("line {}: expected `token` or `label token`", n + 1),
                    })
                }
            };
            tokens.add(label, token, file)?;
        }
        Ok(tokens)
    }

    pub fn load(file: &Path) -> Result<Self, TokensError> {
        let text = std::fs::read_to_string(file).map_err(|e| TokensError::File {
            file: file.into(),
            message: e.to_string(),
        })?;
        Self::parse(&text, file)
    }

    /// Adds `FACTORD_TOKENS`-style comma-separated tokens.
    pub fn extend_from_list(&mut self, list: &str) -> Result<(), TokensError> {
        for (i, token) in list.split(',').map(str::trim).enumerate() {
            if !token.is_empty() {
                self.add(format!("env-{i}"), token, Path::new("FACTORD_TOKENS"))?;
            }
        }
        Ok(())
    }

    fn add(&mut self, label: String, token: &str, source: &Path) -> Result<(), TokensError> {
        // Short tokens are guessable; refuse them rather than run with one.
        if token.len() < 16 || !token.bytes().all(|b| b.is_ascii_graphic()) {
            return Err(TokensError::File {
                file: source.into(),
                message: format!("token `{label}` must be at least 16 printable characters"),
            });
        }
        self.by_token.insert(token.to_string(), label.into());
        Ok(())
    }

    pub fn is_empty(&self) -> bool {
        self.by_token.is_empty()
    }

    pub fn len(&self) -> usize {
        self.by_token.len()
    }

    fn check(&self, header: Option<&HeaderValue>) -> Option<Arc<str>> {
        let value = header?.to_str().ok()?;
        let token = value.strip_prefix("Bearer ")?.trim();
        self.label_of(token)
    }

    /// The label of `token`, when it is one of ours.
    pub fn label_of(&self, token: &str) -> Option<Arc<str>> {
        self.by_token.get(token).cloned()
    }

    /// The web view's cookie, on a read only: GET or HEAD, and not a WebSocket upgrade (whose
    /// stream takes batches). A cookie is sent by the browser by itself; the methods that change
    /// state need the bearer header, which a cross-site page cannot make it send.
    fn check_cookie(&self, request: &Request) -> Option<Arc<str>> {
        let read = matches!(*request.method(), Method::GET | Method::HEAD)
            && !request.headers().contains_key(header::UPGRADE);
        if !read {
            return None;
        }
        request
            .headers()
            .get_all(header::COOKIE)
            .iter()
            .filter_map(|v| v.to_str().ok())
            .flat_map(|v| v.split(';'))
            .filter_map(|pair| pair.trim().strip_prefix(COOKIE)?.strip_prefix('='))
            .find_map(|value| self.label_of(&super::login::unhex(value)?))
    }
}

/// The web view's cookie (see `login`).
pub const COOKIE: &str = "factord_token";

fn unauthorized(message: &str) -> Response {
    let mut response = super::HttpError::from(
        ServiceError::new(ErrorKind::Unauthorized, "unauthorized", message).at("authorization"),
    )
    .into_response();
    response
        .headers_mut()
        .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
    response
}

/// Checks the bearer token and leaves the [`Caller`] in the request: the token's principal,
/// or [`Caller::Anonymous`] on the open routes (health, the pages) without a valid token; 401
/// elsewhere. Which sessions the caller may reach is decided by the service where it resolves
/// the session name, not here from the URL's text.
pub async fn require_token(
    State(tokens): State<Arc<Tokens>>,
    mut request: Request,
    next: Next,
) -> Response {
    let path = request.uri().path();
    let open = path == "/v1/health"
        || path == "/v1/openapi.json"
        || path == "/v1/docs"
        || path == "/"
        || path == "/v1/login"
        || path == "/v1/logout"
        || path.starts_with("/sessions/")
        || path.starts_with("/assets/");
    let principal = tokens
        .check(request.headers().get(header::AUTHORIZATION))
        .or_else(|| tokens.check_cookie(&request));
    let caller = match principal {
        Some(label) => {
            if let Some(connection) = request.extensions().get::<ConnectionContext>() {
                connection.authenticated();
            }
            Caller::Principal(label)
        }
        None if open => {
            request = match super::body_limits::limit_anonymous(request) {
                Ok(request) => request,
                Err(refusal) => return refusal,
            };
            Caller::Anonymous
        }
        None => {
            let message = if request.headers().contains_key(header::AUTHORIZATION) {
                "the bearer token is not valid"
            } else {
                "this server requires `Authorization: Bearer <token>`"
            };
            return unauthorized(message);
        }
    };
    request.extensions_mut().insert(caller);
    request
        .extensions_mut()
        .insert(super::login::LoginTokens(Some(tokens)));
    next.run(request).await
}

/// Without tokens every HTTP caller is trusted (HTTP then listens on loopback only).
pub async fn trust_everyone(mut request: Request, next: Next) -> Response {
    if let Some(connection) = request.extensions().get::<ConnectionContext>() {
        connection.authenticated();
    }
    request.extensions_mut().insert(Caller::Trusted);
    request
        .extensions_mut()
        .insert(super::login::LoginTokens(None));
    next.run(request).await
}
