//! Refuses requests a web page could make the operator's browser send (cross-site requests,
//! DNS rebinding), before any handler (after the bearer-token check, where tokens are on: a
//! browser never sends a token by itself, so those requests are already refused there):
//!
//! - `Host` must name this server: on loopback `localhost`, `127.0.0.1`, `[::1]` or the listen
//!   address's host, plus `http.allowed_hosts`. A rebinding page's requests carry its own name
//!   and are refused (`forbidden_host`, 421). Beyond loopback every route but health needs a
//!   bearer token, which a browser never attaches by itself, so any `Host` is accepted there
//!   unless `http.allowed_hosts` is set. A request without `Host` (HTTP/1.0) is not a
//!   browser's and passes.
//! - Bearer tokens are never attached by a browser by itself; the web view's login cookie is,
//!   but `auth` accepts it on reads only (GET and HEAD, not WebSocket upgrades), and SameSite=
//!   Strict keeps it off cross-site requests altogether.
//! - A request that changes state (any method but GET, HEAD and OPTIONS, and WebSocket upgrades,
//!   which take batches) with an `Origin` must come from the server's own origin (`http://` or
//!   `https://` + its `Host`) or one in `http.allowed_origins` (`forbidden_origin`, 403).
//!   Requests without `Origin` come from programs, not pages, and pass.
//! - Routes that read a JSON body need `Content-Type: application/json` (parameters such as
//!   `charset` allowed): the types a page may send without a CORS preflight (`text/plain`, forms)
//!   are refused (`unsupported_media_type`, 415, field `content-type`). `/v1/jobs` takes graph
//!   files of any type.

use std::collections::HashSet;
use std::net::SocketAddr;
use std::sync::Arc;

use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, Method};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::listener::HttpConfig;
use super::HttpError;
use crate::api::ErrorKind;
use crate::api::ServiceError;

/// What the guard accepts, fixed at start.
#[derive(Debug)]
pub struct HttpGuard {
    /// Host names accepted in `Host` (lower case, IPv6 without brackets); `None`: any.
    hosts: Option<HashSet<String>>,
    /// Origins accepted besides the server's own (lower case, no trailing `/`).
    origins: HashSet<String>,
}

impl HttpGuard {
    /// For a server configured to listen on `listen` and bound to `bound`.
    pub fn new(listen: &str, bound: &SocketAddr, config: &HttpConfig) -> Self {
        let mut hosts: HashSet<String> = config
            .allowed_hosts
            .iter()
            .map(|h| normalise_host(h))
            .collect();
        let checked = bound.ip().is_loopback() || !hosts.is_empty();
        if bound.ip().is_loopback() {
            hosts.extend(["localhost", "127.0.0.1", "::1"].map(String::from));
        }
        if !bound.ip().is_unspecified() {
            hosts.insert(bound.ip().to_string());
            hosts.insert(normalise_host(host_of(listen)));
        }
        let origins = config
            .allowed_origins
            .iter()
            .map(|o| o.trim_end_matches('/').to_ascii_lowercase())
            .collect();
        Self {
            hosts: checked.then_some(hosts),
            origins,
        }
    }

    fn check(&self, method: &Method, path: &str, headers: &HeaderMap) -> Result<(), ServiceError> {
        let host = headers.get(header::HOST).and_then(|v| v.to_str().ok());
        if let (Some(allowed), Some(host)) = (&self.hosts, host) {
            if !allowed.contains(&normalise_host(host_of(host))) {
                return Err(ServiceError::new(
                    ErrorKind::Misdirected,
                    "forbidden_host",
                    format!(
                        "this server does not answer to the name `{host}` (add it to \
                         http.allowed_hosts if it is really this server's)"
                    ),
                )
                .at("host"));
            }
        }
        let changes_state = !matches!(*method, Method::GET | Method::HEAD | Method::OPTIONS)
            || headers.contains_key(header::UPGRADE);
        if let Some(origin) = headers.get(header::ORIGIN).filter(|_| changes_state) {
            let origin = origin.to_str().unwrap_or("").to_ascii_lowercase();
            if !self.same_or_allowed(&origin, host) {
                return Err(ServiceError::new(
                    ErrorKind::Forbidden,
                    "forbidden_origin",
                    format!(
                        "requests from the web page at `{origin}` may not change anything here \
                         (add it to http.allowed_origins to allow it)"
                    ),
                )
                .at("origin"));
            }
        }
        if takes_json(method, path) && !is_json(headers) {
            let sent = headers
                .get(header::CONTENT_TYPE)
                .map_or("none".into(), |v| {
                    format!("`{}`", v.to_str().unwrap_or("?"))
                });
            return Err(ServiceError::new(
                ErrorKind::UnsupportedMediaType,
                "unsupported_media_type",
                format!(
                    "this route reads JSON: send `Content-Type: application/json` (got {sent})"
                ),
            )
            .at("content-type"));
        }
        Ok(())
    }

    fn same_or_allowed(&self, origin: &str, host: Option<&str>) -> bool {
        if self.origins.contains(origin.trim_end_matches('/')) {
            return true;
        }
        let Some(host) = host else {
            return false;
        };
        let host = host.to_ascii_lowercase();
        [("http://", ":80"), ("https://", ":443")]
            .iter()
            .any(|(scheme, default_port)| {
                origin.strip_prefix(scheme).is_some_and(|authority| {
                    let bare = |a: &str| a.strip_suffix(default_port).unwrap_or(a).to_string();
                    bare(authority) == bare(&host)
                })
            })
    }
}

/// The host part of `host[:port]` or `[v6]:port`.
fn host_of(authority: &str) -> &str {
    let authority = authority.trim();
    if let Some(v6) = authority.strip_prefix('[') {
        return v6.split(']').next().unwrap_or(v6);
    }
    match authority.rsplit_once(':') {
        Some((host, port)) if port.bytes().all(|b| b.is_ascii_digit()) => host,
        _ => authority,
    }
}

fn normalise_host(host: &str) -> String {
    host.trim_start_matches('[')
        .trim_end_matches(']')
        .trim_end_matches('.')
        .to_ascii_lowercase()
}

/// The routes whose body is JSON.
fn takes_json(method: &Method, path: &str) -> bool {
    let segments: Vec<&str> = path.trim_end_matches('/').split('/').collect();
    match segments[..] {
        ["", "v1", "sessions"] | ["", "v1", "login"] => *method == Method::POST,
        ["", "v1", "sessions", _, "batches" | "fusion"] => *method == Method::POST,
        ["", "v1", "sessions", _, "auto_optimize"] => *method == Method::PUT,
        _ => false,
    }
}

fn is_json(headers: &HeaderMap) -> bool {
    headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.split(';').next())
        .is_some_and(|essence| essence.trim().eq_ignore_ascii_case("application/json"))
}

/// The middleware (see the module documentation).
pub async fn guard(State(guard): State<Arc<HttpGuard>>, request: Request, next: Next) -> Response {
    match guard.check(request.method(), request.uri().path(), request.headers()) {
        Ok(()) => next.run(request).await,
        Err(refusal) => HttpError::from(refusal).into_response(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn headers(pairs: &[(&'static str, &str)]) -> HeaderMap {
        let mut map = HeaderMap::new();
        for (k, v) in pairs {
            map.insert(*k, v.parse().unwrap());
        }
        map
    }

    #[test]
    fn loopback_names_and_own_origin_pass_foreign_ones_do_not() {
        let bound: SocketAddr = "127.0.0.1:8080".parse().unwrap();
        let guard = HttpGuard::new("127.0.0.1:8080", &bound, &HttpConfig::default());
        let post = |h: &[(&'static str, &str)]| {
            guard
                .check(&Method::POST, "/v1/sessions", &headers(h))
                .map_err(|e| e.body.code)
        };
        let json = ("content-type", "application/json; charset=utf-8");
        assert_eq!(post(&[("host", "localhost:8080"), json]), Ok(()));
        assert_eq!(post(&[("host", "[::1]:8080"), json]), Ok(()));
        let own = [
            ("host", "127.0.0.1:8080"),
            ("origin", "http://127.0.0.1:8080"),
            json,
        ];
        assert_eq!(post(&own), Ok(()));
        let evil = [("host", "evil.example"), json];
        assert_eq!(post(&evil), Err("forbidden_host".into()));
        let foreign = [
            ("host", "localhost:8080"),
            ("origin", "http://evil.example"),
            json,
        ];
        assert_eq!(post(&foreign), Err("forbidden_origin".into()));
        let text = [("host", "localhost:8080"), ("content-type", "text/plain")];
        assert_eq!(post(&text), Err("unsupported_media_type".into()));
        let job = guard.check(
            &Method::POST,
            "/v1/jobs",
            &headers(&[("host", "localhost")]),
        );
        assert!(job.is_ok());
    }

    #[test]
    fn beyond_loopback_any_host_unless_listed() {
        let bound: SocketAddr = "0.0.0.0:8080".parse().unwrap();
        let open = HttpGuard::new("0.0.0.0:8080", &bound, &HttpConfig::default());
        let get = headers(&[("host", "robot-17.lan:8080")]);
        assert!(open.check(&Method::GET, "/v1/sessions", &get).is_ok());
        let config = HttpConfig {
            allowed_hosts: vec!["factord.lan".into()],
            ..HttpConfig::default()
        };
        let listed = HttpGuard::new("0.0.0.0:8080", &bound, &config);
        assert!(listed.check(&Method::GET, "/v1/sessions", &get).is_err());
        let ok = headers(&[("host", "FACTORD.LAN:8080")]);
        assert!(listed.check(&Method::GET, "/v1/sessions", &ok).is_ok());
    }
}
