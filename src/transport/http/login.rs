//! The web view's login: `POST /v1/login` with `{"token": …}` checks the token (exactly, in
//! constant time, failures throttled per peer) and answers with an `HttpOnly; SameSite=Strict`
//! cookie naming a login session (see `web_sessions`: an opaque id, not the token), which
//! [`super::auth`] accepts like the bearer header, but only on reads (GET and HEAD, WebSocket
//! upgrades excepted): a cross-site form cannot change anything with it, and EventSource, which
//! cannot send headers, can stream. `POST /v1/logout` ends the session and clears the cookie.
//! The cookie is `Secure` when the login came through TLS in front (`X-Forwarded-Proto: https`
//! or `Forwarded: …proto=https`). Without tokens there is nothing to log in to (`auth: false`).

use std::net::IpAddr;
use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::rejection::BytesRejection;
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::IntoResponse;
use axum::{Extension, Json};
use serde::{Deserialize, Serialize};

use super::auth::{Tokens, COOKIE};
use super::errors::{body_error, HttpResult};
use super::openapi::*;
use super::web_sessions::LIFETIME;
use crate::api::ErrorKind;
use crate::service::{parse_json, ServiceError};

/// The tokens a login is checked against (none: tokens are off) and the peer it comes from
/// (its failures are throttled), left by the auth layer.
#[derive(Clone)]
pub struct LoginTokens(pub Option<Arc<Tokens>>, pub Option<IpAddr>);

/// A token to exchange for the web view's cookie.
#[derive(Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct LoginRequest {
    pub token: String,
}

#[derive(Serialize, utoipa::ToSchema)]
pub struct LoginReply {
    /// Whether this server requires tokens at all.
    pub auth: bool,
    /// The label of the token logged in with.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub principal: Option<String>,
}

/// Exchange a token for an `HttpOnly; SameSite=Strict` cookie that authenticates reads (GET,
/// HEAD, the event stream) from the web view; changes still need the bearer header.
#[utoipa::path(post, path = "/v1/login", tag = "web",
    request_body = LoginRequest,
    responses((status = 200,
            description = "Logged in (`Set-Cookie`), or tokens are off (`auth: false`, no cookie).",
            body = LoginReply), (status = 400, response = BadRequest), (status = 401, response = Unauthorized), (status = 403, response = Forbidden), (status = 408, response = RequestTimeout), (status = 413, response = PayloadTooLarge), (status = 415, response = UnsupportedMediaType), (status = 421, response = Misdirected), (status = 429, response = TooMany)))]
pub(super) async fn login(
    Extension(LoginTokens(tokens, peer)): Extension<LoginTokens>,
    headers: HeaderMap,
    body: Result<Bytes, BytesRejection>,
) -> HttpResult {
    let request: LoginRequest = parse_json(&body.map_err(body_error)?)?;
    let Some(tokens) = tokens else {
        let reply = LoginReply {
            auth: false,
            principal: None,
        };
        return Ok(Json(reply).into_response());
    };
    if let Some(peer) = peer {
        tokens.failures.check(peer)?;
    }
    // Exactly the token: one with anything around it is another token.
    let Some(label) = tokens.label_of(&request.token) else {
        if let Some(peer) = peer {
            tokens.failures.failed(peer);
        }
        return Err(ServiceError::new(
            ErrorKind::Unauthorized,
            "unauthorized",
            "the token is not valid",
        )
        .at("token")
        .into());
    };
    let id = tokens
        .web_sessions
        .open(Arc::clone(&label))
        .map_err(|e| ServiceError::internal(e.to_string()))?;
    let secure = if behind_tls(&headers) { "; Secure" } else { "" };
    let cookie = format!(
        "{COOKIE}={id}; Path=/; HttpOnly; SameSite=Strict; Max-Age={}{secure}",
        LIFETIME.as_secs()
    );
    let reply = LoginReply {
        auth: true,
        principal: Some(label.to_string()),
    };
    Ok(([(header::SET_COOKIE, cookie)], Json(reply)).into_response())
}

/// End the web view's login session and clear its cookie.
#[utoipa::path(post, path = "/v1/logout", tag = "web",
    responses((status = 204, description = "The login session is ended and the cookie cleared."), (status = 403, response = Forbidden), (status = 421, response = Misdirected)))]
pub(super) async fn logout(
    Extension(LoginTokens(tokens, _)): Extension<LoginTokens>,
    headers: HeaderMap,
) -> impl IntoResponse {
    if let Some(tokens) = tokens {
        for id in super::auth::cookie_values(&headers) {
            tokens.web_sessions.close(id);
        }
    }
    let secure = if behind_tls(&headers) { "; Secure" } else { "" };
    let cookie = format!("{COOKIE}=; Path=/; HttpOnly; SameSite=Strict; Max-Age=0{secure}");
    (StatusCode::NO_CONTENT, [(header::SET_COOKIE, cookie)])
}

/// Whether the request came through TLS terminated in front of the server (a proxy says so;
/// a client that claims it only gets a cookie its browser will not send back over plain HTTP).
fn behind_tls(headers: &HeaderMap) -> bool {
    let forwarded_proto = headers
        .get_all("x-forwarded-proto")
        .iter()
        .filter_map(|v| v.to_str().ok())
        .any(|v| v.trim().eq_ignore_ascii_case("https"));
    let forwarded = headers
        .get_all(header::FORWARDED)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split([';', ',']))
        .any(|pair| pair.trim().eq_ignore_ascii_case("proto=https"));
    forwarded_proto || forwarded
}

#[cfg(test)]
mod tests {
    use axum::http::HeaderMap;

    #[test]
    fn tls_in_front_is_what_the_proxy_says() {
        let mut headers = HeaderMap::new();
        assert!(!super::behind_tls(&headers));
        headers.insert("x-forwarded-proto", "https".parse().unwrap());
        assert!(super::behind_tls(&headers));
        let mut headers = HeaderMap::new();
        headers.insert("forwarded", "for=192.0.2.1;proto=https".parse().unwrap());
        assert!(super::behind_tls(&headers));
    }
}
