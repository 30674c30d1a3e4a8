//! HTTP in a fleet: any instance answers for any session. A request under
//! `/v1/sessions/<s>/…` for a session another instance owns is forwarded to the owner's
//! advertised URL (method, path, query, headers, body; the answer streamed back, so SSE works
//! through it; with a fleet secret the caller's token and cookies stay here and the owner gets
//! a signed assertion of the caller instead, `fleet_caller`); a WebSocket is redirected there (307). `POST /v1/sessions`
//! goes to the owner of the name (an unnamed creation is named first, fleet-wide), and
//! `GET /v1/sessions` lists every instance's sessions.
//!
//! This runs after the token check and the cross-site guard (the owner runs them again: every
//! instance has the same tokens). A forwarded request carries `Factord-Forwarded-By`; one that
//! reaches an instance that does not own the session (ownership moved meanwhile) is answered
//! 503 `session_moving` with Retry-After 1 instead of being forwarded again, as is a request
//! for a session in the middle of a move or whose owner cannot be reached, or one for a
//! session that was released here between routing and its handler.

use std::sync::Arc;
use std::time::Duration;

use axum::body::{Body, Bytes};
use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, HeaderName, HeaderValue, Method, StatusCode, Uri};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use hyper_util::client::legacy::connect::HttpConnector;
use hyper_util::client::legacy::Client;
use hyper_util::rt::TokioExecutor;

use super::auth::Tokens;
use super::{fleet_caller, HttpError};
use crate::service::fleet::{merge_session_lists, moving, Fleet, Route};
use crate::service::{Caller, Command, Recording, Reply, Service, ServiceError};

/// Names the instance a request was forwarded by: its receiver answers, never forwards.
pub const FORWARDED_BY: HeaderName = HeaderName::from_static("factord-forwarded-by");

/// How long connecting to another instance may take before the session counts as moving.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(2);
/// How long another instance's session list may take.
const LIST_TIMEOUT: Duration = Duration::from_secs(3);

pub struct Forwarder {
    service: Arc<Service>,
    client: Client<HttpConnector, Body>,
    max_body_bytes: usize,
    tokens: Option<Arc<Tokens>>,
}

impl Forwarder {
    /// The forwarder of a service in a fleet; `None` outside one.
    pub fn for_fleet(
        service: &Arc<Service>,
        max_body_bytes: usize,
        tokens: Option<Arc<Tokens>>,
    ) -> Option<Arc<Self>> {
        service.fleet()?;
        let mut connector = HttpConnector::new();
        connector.set_connect_timeout(Some(CONNECT_TIMEOUT));
        connector.set_nodelay(true);
        let client = Client::builder(TokioExecutor::new()).build(connector);
        Some(Arc::new(Self {
            service: Arc::clone(service),
            client,
            max_body_bytes,
            tokens,
        }))
    }

    /// The `Authorization` a forwarded request carries: its own, or for one authenticated by a
    /// login cookie (which only this process knows) a bearer token of the same principal.
    /// Cookies authenticate reads only, so only reads are forwarded this way.
    fn authorization(&self, request: &Request) -> Option<HeaderValue> {
        if let Some(own) = request.headers().get(header::AUTHORIZATION) {
            return Some(own.clone());
        }
        match request.extensions().get::<Caller>() {
            Some(Caller::Principal(label)) => self.tokens.as_ref()?.bearer_for(label),
            _ => None,
        }
    }
}

/// The middleware: see the module's documentation.
pub async fn forward(State(f): State<Arc<Forwarder>>, request: Request, next: Next) -> Response {
    let forwarded = request.headers().contains_key(FORWARDED_BY);
    let path = request.uri().path().to_string();
    if path == "/v1/sessions" {
        return match *request.method() {
            Method::GET if !forwarded => list(&f, request).await,
            Method::POST => create(&f, request, next, forwarded).await,
            _ => next.run(request).await,
        };
    }
    let Some(name) = path
        .strip_prefix("/v1/sessions/")
        .and_then(|rest| rest.split('/').next())
        .map(percent_decoded)
    else {
        return next.run(request).await;
    };
    match f.service.route(&name) {
        Route::Local => {
            // Loaded here when routed, gone when the handler looked (released to a new owner
            // meanwhile, as when a stopped instance resumes to find itself superseded): its
            // 404 would say the session does not exist, while it only moved. Nothing was
            // applied, so the client may retry where it is now. A session deleted meanwhile
            // routes here again (its directory is gone) and keeps its 404.
            let was_here = f.service.session(&name).is_ok();
            let response = next.run(request).await;
            if was_here
                && response.status() == StatusCode::NOT_FOUND
                && !matches!(f.service.route(&name), Route::Local)
            {
                return refuse(&name);
            }
            response
        }
        Route::Remote {
            http: Some(url), ..
        } if !forwarded => {
            if request.headers().contains_key(header::UPGRADE) {
                redirect(&url, request.uri())
            } else {
                proxy(&f, &url, request).await
            }
        }
        Route::Remote { .. } | Route::Moving => refuse(&name),
    }
}

fn refuse(name: &str) -> Response {
    HttpError::from(moving(name)).into_response()
}

/// A WebSocket cannot be forwarded here: the client is sent to the owner.
fn redirect(base: &str, uri: &Uri) -> Response {
    let target = format!("{base}{}", uri.path_and_query().map_or("/", |p| p.as_str()));
    match HeaderValue::from_str(&target) {
        Ok(location) => (
            StatusCode::TEMPORARY_REDIRECT,
            [(header::LOCATION, location)],
        )
            .into_response(),
        Err(_) => {
            HttpError::from(ServiceError::internal("unrepresentable owner URL")).into_response()
        }
    }
}

/// Headers that belong to one connection, not to the request or answer.
const HOP_BY_HOP: [&str; 8] = [
    "connection",
    "keep-alive",
    "proxy-authenticate",
    "proxy-authorization",
    "te",
    "trailer",
    "transfer-encoding",
    "upgrade",
];

fn strip_hop_by_hop(headers: &mut HeaderMap) {
    for name in HOP_BY_HOP {
        headers.remove(name);
    }
}

/// Sends `request` to the instance at `base` and streams its answer back.
async fn proxy(f: &Forwarder, base: &str, mut request: Request) -> Response {
    let name = session_of(request.uri().path());
    let path_and_query = request
        .uri()
        .path_and_query()
        .map_or("/", |p| p.as_str())
        .to_string();
    let target = format!("{base}{path_and_query}");
    let Ok(uri) = target.parse::<Uri>() else {
        return HttpError::from(ServiceError::internal(format!("bad owner URL `{target}`")))
            .into_response();
    };
    *request.uri_mut() = uri;
    let authorization = f.authorization(&request);
    let headers = request.headers_mut();
    strip_hop_by_hop(headers);
    if let Some(authorization) = authorization {
        headers.insert(header::AUTHORIZATION, authorization);
    }
    // The client names the owner in `Host`; the origin was checked here already.
    headers.remove(header::HOST);
    headers.remove(header::ORIGIN);
    if let Some(fleet) = f.service.fleet() {
        if let Ok(me) = HeaderValue::from_str(fleet.instance()) {
            headers.insert(FORWARDED_BY, me);
        }
        let caller = caller_of(&request);
        let method = request.method().clone();
        let headers = request.headers_mut();
        fleet_caller::assert_caller(fleet, headers, &method, &path_and_query, &caller);
    }
    match f.client.request(request).await {
        Ok(answer) => {
            let (mut parts, body) = answer.into_parts();
            strip_hop_by_hop(&mut parts.headers);
            Response::from_parts(parts, Body::new(body))
        }
        Err(e) => {
            tracing::warn!(
                owner = base,
                "fleet: forwarding an HTTP request failed: {e}"
            );
            refuse(&name)
        }
    }
}

/// `POST /v1/sessions`: named (fleet-wide when unnamed), then created by the name's owner.
async fn create(f: &Forwarder, request: Request, next: Next, forwarded: bool) -> Response {
    let (mut parts, body) = request.into_parts();
    let bytes = match axum::body::to_bytes(body, f.max_body_bytes).await {
        Ok(bytes) => bytes,
        Err(e) => return HttpError::from(too_large(e)).into_response(),
    };
    let mut body_json = match serde_json::from_slice::<serde_json::Value>(&bytes) {
        Ok(v) if v.is_object() => v,
        // The handler says what is wrong with it.
        _ => {
            return next
                .run(Request::from_parts(parts, Body::from(bytes)))
                .await
        }
    };
    let bytes = if body_json.get("session").is_none_or(|s| s.is_null()) {
        let Some(fleet) = f.service.fleet().cloned() else {
            return next
                .run(Request::from_parts(parts, Body::from(bytes)))
                .await;
        };
        match tokio::task::spawn_blocking(move || fleet.generate_name()).await {
            Ok(Ok(name)) => body_json["session"] = serde_json::Value::String(name),
            Ok(Err(e)) => return HttpError::from(e).into_response(),
            Err(e) => {
                return HttpError::from(ServiceError::internal(e.to_string())).into_response()
            }
        }
        parts.headers.remove(header::CONTENT_LENGTH);
        Bytes::from(serde_json::to_vec(&body_json).expect("JSON serialises"))
    } else {
        bytes
    };
    let name = body_json["session"]
        .as_str()
        .unwrap_or_default()
        .to_string();
    let request = Request::from_parts(parts, Body::from(bytes));
    match f.service.route(&name) {
        Route::Local => next.run(request).await,
        Route::Remote {
            http: Some(url), ..
        } if !forwarded => proxy(f, &url, request).await,
        Route::Remote { .. } | Route::Moving => refuse(&name),
    }
}

fn too_large(e: axum::Error) -> ServiceError {
    ServiceError::new(
        crate::api::ErrorKind::TooLarge,
        "body_too_large",
        format!("the request body could not be read within the limit: {e}"),
    )
}

/// `GET /v1/sessions`: this instance's sessions and every other live instance's, merged.
/// The caller the checks before this middleware found (none: anonymous, failing closed).
fn caller_of(request: &Request) -> Caller {
    request
        .extensions()
        .get::<Caller>()
        .cloned()
        .unwrap_or(Caller::Anonymous)
}

async fn list(f: &Forwarder, request: Request) -> Response {
    let caller = caller_of(&request);
    let own = match f
        .service
        .execute(&caller, Command::ListSessions, Recording::History)
        .await
    {
        Ok(Reply::Sessions(list)) => list
            .sessions
            .into_iter()
            .map(|s| serde_json::to_value(s).expect("session info serialises"))
            .collect(),
        Ok(_) => Vec::new(),
        Err(e) => return HttpError::from(e).into_response(),
    };
    let authorization = f.authorization(&request);
    let Some(fleet) = f.service.fleet() else {
        return (
            StatusCode::OK,
            axum::Json(serde_json::json!({ "sessions": own })),
        )
            .into_response();
    };
    let others: Vec<String> = fleet
        .live()
        .into_iter()
        .filter(|id| id != fleet.instance())
        .filter_map(|id| fleet.member(&id).and_then(|m| m.http))
        .collect();
    let asks = others
        .iter()
        .map(|url| remote_list(f, fleet, url, authorization.clone(), &caller));
    let mut lists = futures_util::future::join_all(asks).await;
    lists.push(own);
    let sessions = merge_session_lists(lists);
    (
        StatusCode::OK,
        axum::Json(serde_json::json!({ "sessions": sessions })),
    )
        .into_response()
}

/// Another instance's own sessions (empty when it does not answer in time).
async fn remote_list(
    f: &Forwarder,
    fleet: &Fleet,
    base: &str,
    authorization: Option<HeaderValue>,
    caller: &Caller,
) -> Vec<serde_json::Value> {
    let Ok(mut request) = Request::get(format!("{base}/v1/sessions")).body(Body::empty()) else {
        return Vec::new();
    };
    let headers = request.headers_mut();
    if let Some(a) = authorization {
        headers.insert(header::AUTHORIZATION, a);
    }
    if let Ok(me) = HeaderValue::from_str(fleet.instance()) {
        headers.insert(FORWARDED_BY, me);
    }
    fleet_caller::assert_caller(fleet, headers, &Method::GET, "/v1/sessions", caller);
    let ask = async {
        let answer = f.client.request(request).await.ok()?;
        if !answer.status().is_success() {
            return None;
        }
        let bytes = axum::body::to_bytes(Body::new(answer.into_body()), 64 << 20)
            .await
            .ok()?;
        let mut v: serde_json::Value = serde_json::from_slice(&bytes).ok()?;
        match v.get_mut("sessions").map(serde_json::Value::take) {
            Some(serde_json::Value::Array(list)) => Some(list),
            _ => None,
        }
    };
    match tokio::time::timeout(LIST_TIMEOUT, ask).await {
        Ok(Some(list)) => list,
        _ => {
            tracing::warn!(instance = base, "fleet: no session list from this instance");
            Vec::new()
        }
    }
}

fn session_of(path: &str) -> String {
    path.strip_prefix("/v1/sessions/")
        .and_then(|rest| rest.split('/').next())
        .map(percent_decoded)
        .unwrap_or_default()
}

/// A path segment with its `%XX` escapes decoded (as the router decodes it).
fn percent_decoded(segment: &str) -> String {
    if !segment.contains('%') {
        return segment.to_string();
    }
    let bytes = segment.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        let hex = bytes
            .get(i + 1..i + 3)
            .and_then(|h| std::str::from_utf8(h).ok())
            .and_then(|h| u8::from_str_radix(h, 16).ok());
        match (bytes[i], hex) {
            (b'%', Some(b)) => {
                out.push(b);
                i += 3;
            }
            (b, _) => {
                out.push(b);
                i += 1;
            }
        }
    }
    String::from_utf8_lossy(&out).into_owned()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn session_names_are_read_as_the_router_decodes_them() {
        assert_eq!(session_of("/v1/sessions/robot-1/batches"), "robot-1");
        assert_eq!(session_of("/v1/sessions/%72obot"), "robot");
        assert_eq!(session_of("/v1/sessions/a%2"), "a%2");
        assert_eq!(session_of("/v1/health"), "");
    }
}
