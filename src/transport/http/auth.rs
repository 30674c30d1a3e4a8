//! Bearer-token authentication for HTTP, and session ownership.
//!
//! Tokens come from a file (`auth.tokens_file`, one `label token` or bare `token` per line, `#`
//! comments) and/or `FACTORD_TOKENS` (comma-separated). They are required automatically when
//! HTTP listens beyond loopback. With tokens in force every route but `GET /v1/health`, the web
//! pages and the API's description (`/v1/openapi.json`, `/v1/docs`: not secret, like the pages'
//! own code) needs `Authorization: Bearer <token>` (401 otherwise), or on reads (GET and HEAD,
//! not WebSocket upgrades) the web view's cookie set by `POST /v1/login` (see `login`): a
//! cross-site form cannot change anything with it. A bearer header, when present, is the only
//! credential looked at (a wrong one is not rescued by a valid cookie); tokens are compared
//! exactly, in constant time, and a peer's failures are throttled (see `throttle`). A session
//! belongs to the
//! label of the token that created it: to any other caller it does not exist (404), nor is it
//! listed or counted (see `service::caller`). Sessions created over an unauthenticated zenoh or
//! before tokens were configured belong to nobody and are reachable with any valid token.
//!
//! `GET /metrics` counts every tenant's sessions, memory and failures, so with several token
//! labels it answers only to the operators (`auth.operators`); a single label is its own
//! operator (there is no other tenant to learn about). Anyone else gets 403 `operator_only`.

use std::collections::HashSet;
use std::net::IpAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, HeaderValue, Method};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::admission::ConnectionContext;
use super::throttle::FailureThrottle;
use super::web_sessions::WebSessions;
use crate::api::ErrorKind;
use crate::service::{Caller, ServiceError};

#[derive(Debug, Default)]
pub struct Tokens {
    /// (token, label), compared in constant time (see [`Tokens::label_of`]).
    tokens: Vec<(Box<[u8]>, Arc<str>)>,
    /// Failed authentications per peer.
    pub(super) failures: FailureThrottle,
    /// The web view's logins, which its cookie names.
    pub(super) web_sessions: WebSessions,
    /// The labels that may read server-wide figures (`auth.operators`); `None`: not configured.
    operators: Option<HashSet<Arc<str>>>,
}

#[derive(Debug, thiserror::Error)]
pub enum TokensError {
    #[error("tokens file {file}: {message}")]
    File { file: PathBuf, message: String },
    #[error("{0}")]
    Operators(String),
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
        self.tokens
            .retain(|(known, _)| **known != *token.as_bytes());
        self.tokens.push((token.as_bytes().into(), label.into()));
        Ok(())
    }

    /// Sets the labels that may read `/metrics`; each must be a label of a configured token.
    pub fn set_operators(&mut self, labels: &[String]) -> Result<(), TokensError> {
        let known = self.labels();
        let mut operators = HashSet::new();
        for label in labels {
            let known = known.iter().find(|k| ****k == **label).ok_or_else(|| {
                TokensError::Operators(format!(
                    "auth.operators names `{label}`, which is the label of no token"
                ))
            })?;
            operators.insert((*known).clone());
        }
        self.operators = Some(operators);
        Ok(())
    }

    /// The distinct labels of the configured tokens.
    fn labels(&self) -> Vec<&Arc<str>> {
        let mut labels: Vec<&Arc<str>> = self.tokens.iter().map(|(_, label)| label).collect();
        labels.sort();
        labels.dedup();
        labels
    }

    /// Whether several tenants share this server and no operator is named: `/metrics` is then
    /// refused to everyone (the server says so at start).
    pub fn metrics_closed(&self) -> bool {
        self.operators.is_none() && self.labels().len() > 1
    }

    /// Whether `label` may read server-wide figures: a listed operator, or, with none listed,
    /// the only label there is.
    fn is_operator(&self, label: &str) -> bool {
        match &self.operators {
            Some(operators) => operators.contains(label),
            None => self.labels().len() == 1,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.tokens.is_empty()
    }

    pub fn len(&self) -> usize {
        self.tokens.len()
    }

    /// The label of `token` exactly (no trimming, no prefix), when it is one of ours. Every
    /// token is compared over its whole length, whatever the guess: how long this takes says
    /// nothing about how much of a guess was right.
    pub fn label_of(&self, token: &str) -> Option<Arc<str>> {
        let mut found = None;
        for (known, label) in &self.tokens {
            if constant_time_eq(known, token.as_bytes()) {
                found = Some(label);
            }
        }
        found.cloned()
    }

    /// `Bearer <token>` for a token of `label`: what a request authenticated by a login cookie
    /// carries when it is forwarded to another instance of a fleet, which shares the tokens
    /// but not this process's logins.
    pub(super) fn bearer_for(&self, label: &str) -> Option<HeaderValue> {
        let (token, _) = self.tokens.iter().find(|(_, l)| &**l == label)?;
        let token = std::str::from_utf8(token).ok()?;
        HeaderValue::from_str(&format!("Bearer {token}")).ok()
    }

    /// The principal a request's credential names; `Err` when it presents one that is wrong.
    fn principal(&self, presented: &Presented<'_>) -> Result<Option<Arc<str>>, ()> {
        let label = match presented {
            Presented::Nothing => return Ok(None),
            Presented::Bearer(token) => token.and_then(|t| self.label_of(t)),
            Presented::Cookies(ids) => ids.iter().find_map(|id| self.web_sessions.label_of(id)),
        };
        label.map(Some).ok_or(())
    }
}

/// Equal bytes, in a time that depends on `known`'s length alone.
fn constant_time_eq(known: &[u8], guess: &[u8]) -> bool {
    let mut diff = u8::from(known.len() != guess.len());
    for (i, k) in known.iter().enumerate() {
        diff |= k ^ guess.get(i).copied().unwrap_or(0);
    }
    std::hint::black_box(diff) == 0
}

/// The credential a request presents. A bearer header is the only one looked at when present:
/// a wrong bearer token is never rescued by a valid cookie. The web view's cookie counts on a
/// read only: GET or HEAD, and not a WebSocket upgrade (whose stream takes batches). A cookie
/// is sent by the browser by itself; the methods that change state need the bearer header,
/// which a cross-site page cannot make it send.
enum Presented<'a> {
    Nothing,
    /// The token after `Bearer `; `None` when the header is not a bearer token at all.
    Bearer(Option<&'a str>),
    Cookies(Vec<&'a str>),
}

impl<'a> Presented<'a> {
    fn of(request: &'a Request) -> Self {
        if let Some(value) = request.headers().get(header::AUTHORIZATION) {
            return Self::Bearer(value.to_str().ok().and_then(|v| v.strip_prefix("Bearer ")));
        }
        let read = matches!(*request.method(), Method::GET | Method::HEAD)
            && !request.headers().contains_key(header::UPGRADE);
        if !read {
            return Self::Nothing;
        }
        let cookies: Vec<&str> = cookie_values(request.headers()).collect();
        match cookies.is_empty() {
            true => Self::Nothing,
            false => Self::Cookies(cookies),
        }
    }
}

/// The web view's cookie (see `login`).
pub const COOKIE: &str = "factord_session";

/// The values of the web view's cookie in `headers`.
pub(super) fn cookie_values(headers: &HeaderMap) -> impl Iterator<Item = &str> {
    headers
        .get_all(header::COOKIE)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(';'))
        .filter_map(|pair| pair.trim().strip_prefix(COOKIE)?.strip_prefix('='))
}

/// 403 for a valid token that is not an operator's on an operator-only route.
fn operator_only(label: &str) -> Response {
    super::HttpError::from(
        ServiceError::new(
            ErrorKind::Forbidden,
            "operator_only",
            format!(
                "`/metrics` shows every tenant's figures and answers only to the token labels \
                 listed in `auth.operators` (--operators); `{label}` is not one of them"
            ),
        )
        .at("authorization"),
    )
    .into_response()
}

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
    let peer = request
        .extensions()
        .get::<ConnectionContext>()
        .map(|c| c.peer.ip());
    // A request a fleet member forwarded, whose asserted caller was verified (`fleet_caller`):
    // it runs as that caller, and its connection (another member's) counts as authenticated.
    let asserted = request
        .extensions()
        .get::<super::fleet_caller::AssertedCaller>()
        .map(|a| a.principal());
    let principal = match asserted {
        Some(principal) => principal,
        None => match authenticate(&tokens, &request, peer, open) {
            Ok(principal) => principal,
            Err(refusal) => return refusal,
        },
    };
    let caller = match principal {
        Some(label) if path == "/metrics" && !tokens.is_operator(&label) => {
            return operator_only(&label);
        }
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
        None => return unauthorized("this server requires `Authorization: Bearer <token>`"),
    };
    request.extensions_mut().insert(caller);
    request
        .extensions_mut()
        .insert(super::login::LoginTokens(Some(tokens), peer));
    next.run(request).await
}

/// The principal of the request's credential (`None`: it presents none, or on an `open` route
/// one that is wrong or is not looked at). Elsewhere 401 for a wrong credential, and 429 for
/// a bearer token from a peer with too many failures. Only bearer tokens (and logins) are
/// throttled: they are the guessable secrets. A login cookie is 32 random bytes, and a browser
/// holding a stale one (after a restart) must not lock its own address out of logging in.
// A Response is large, but the refusals are the rare path and are sent as they are.
#[allow(clippy::result_large_err)]
fn authenticate(
    tokens: &Tokens,
    request: &Request,
    peer: Option<IpAddr>,
    open: bool,
) -> Result<Option<Arc<str>>, Response> {
    let presented = Presented::of(request);
    let bearer = match presented {
        Presented::Nothing => return Ok(None),
        Presented::Bearer(_) => peer,
        Presented::Cookies(_) => None,
    };
    if let Some(throttled) = bearer.and_then(|p| tokens.failures.check(p).err()) {
        return match open {
            true => Ok(None),
            false => Err(super::HttpError::from(throttled).into_response()),
        };
    }
    if let Ok(principal) = tokens.principal(&presented) {
        return Ok(principal);
    }
    if let Some(peer) = bearer {
        tokens.failures.failed(peer);
    }
    match (open, presented) {
        (true, _) => Ok(None),
        (false, Presented::Bearer(_)) => Err(unauthorized("the bearer token is not valid")),
        (false, _) => Err(unauthorized("the login cookie is not valid (log in again)")),
    }
}

/// Without tokens every HTTP caller is trusted (HTTP then listens on loopback only).
pub async fn trust_everyone(mut request: Request, next: Next) -> Response {
    if let Some(connection) = request.extensions().get::<ConnectionContext>() {
        connection.authenticated();
    }
    request.extensions_mut().insert(Caller::Trusted);
    request
        .extensions_mut()
        .insert(super::login::LoginTokens(None, None));
    next.run(request).await
}
