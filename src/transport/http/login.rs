//! The web view's login: `POST /v1/login` with `{"token": …}` checks the token and answers with
//! an `HttpOnly; SameSite=Strict` cookie holding it, which [`super::auth`] accepts like the
//! bearer header, but only on reads (GET and HEAD, WebSocket upgrades excepted): a cross-site
//! form cannot change anything with it, and EventSource, which cannot send headers, can stream.
//! `POST /v1/logout` clears it. Without tokens there is nothing to log in to (`auth: false`).

use std::net::IpAddr;
use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::rejection::BytesRejection;
use axum::http::{header, StatusCode};
use axum::response::IntoResponse;
use axum::{Extension, Json};
use serde::{Deserialize, Serialize};

use super::auth::{Tokens, COOKIE};
use super::errors::{body_error, HttpResult};
use super::openapi::*;
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

/// Hours the cookie lasts.
const COOKIE_HOURS: u64 = 12;

/// Exchange a token for an `HttpOnly; SameSite=Strict` cookie that authenticates reads (GET,
/// HEAD, the event stream) from the web view; changes still need the bearer header.
#[utoipa::path(post, path = "/v1/login", tag = "web",
    request_body = LoginRequest,
    responses((status = 200,
            description = "Logged in (`Set-Cookie`), or tokens are off (`auth: false`, no cookie).",
            body = LoginReply), (status = 400, response = BadRequest), (status = 401, response = Unauthorized), (status = 403, response = Forbidden), (status = 408, response = RequestTimeout), (status = 413, response = PayloadTooLarge), (status = 415, response = UnsupportedMediaType), (status = 421, response = Misdirected), (status = 429, response = TooMany)))]
pub(super) async fn login(
    Extension(LoginTokens(tokens, peer)): Extension<LoginTokens>,
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
    let cookie = format!(
        "{COOKIE}={}; Path=/; HttpOnly; SameSite=Strict; Max-Age={}",
        hex(&request.token),
        COOKIE_HOURS * 3600
    );
    let reply = LoginReply {
        auth: true,
        principal: Some(label.to_string()),
    };
    Ok(([(header::SET_COOKIE, cookie)], Json(reply)).into_response())
}

/// Clear the web view's cookie.
#[utoipa::path(post, path = "/v1/logout", tag = "web",
    responses((status = 204, description = "The cookie is cleared."), (status = 403, response = Forbidden), (status = 421, response = Misdirected)))]
pub(super) async fn logout() -> impl IntoResponse {
    let cookie = format!("{COOKIE}=; Path=/; HttpOnly; SameSite=Strict; Max-Age=0");
    (StatusCode::NO_CONTENT, [(header::SET_COOKIE, cookie)])
}

/// Tokens are printable ASCII, but `;`, `,`, `"`, `\` and spaces are not cookie characters:
/// the cookie holds the token in hex.
fn hex(text: &str) -> String {
    hex::encode(text)
}

/// The token a cookie value holds (see [`hex`]).
pub(super) fn unhex(text: &str) -> Option<String> {
    String::from_utf8(hex::decode(text).ok()?).ok()
}

#[cfg(test)]
mod tests {
    #[test]
    fn cookie_values_round_trip() {
        let token = "a;b,c\"d\\e f0123456789";
        assert_eq!(super::unhex(&super::hex(token)).as_deref(), Some(token));
        assert_eq!(super::unhex("zz"), None);
        assert_eq!(super::unhex("abc"), None);
    }
}
