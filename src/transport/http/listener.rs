//! The HTTP accept loop: HTTP/1.1 connections served by hyper under a cap, with header and
//! idle timeouts, so idle or half-open sockets cannot take every file descriptor.
//!
//! - Up to `max_connections` connections are served normally.
//! - With tokens on, a connection that has not yet authenticated gives its slot to a newcomer
//!   once the cap is reached (see `admission`).
//! - Beyond the cap, a small reserve ([`RESERVE_CONNECTIONS`]) still answers `GET /v1/health`
//!   and `GET /metrics` (one request per connection, a short header timeout); anything else
//!   there gets 503 `too_many_connections` and the connection closes. When the reserve is full,
//!   a newcomer takes the place of the oldest reserve connection that has not sent a request
//!   yet, so sockets that only hold a place cannot keep probes out.
//! - Beyond that, connections are closed as soon as they are accepted.
//!
//! A request body must keep up a minimum rate (see `body_limits`): a handler waiting for one
//! counts as work, which the idle timeout below does not interrupt.
//!
//! A connection has `header_timeout_ms` to deliver a request head, counted from when the server
//! starts waiting for one (a new connection, or a kept-alive one after its last answer). One on
//! which no byte moves either way for `idle_timeout_ms` while no handler is working on one of
//! its requests is closed (a client that stopped reading its answer). Upgraded WebSockets are
//! outside both: they live as long as the session's stream, and still count under the cap.

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use axum::body::Body;
use axum::extract::Request;
use axum::http::{header, HeaderValue, Method};
use axum::response::{IntoResponse, Response};
use axum::Router;
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use serde::{Deserialize, Serialize};
use tokio::net::TcpListener;
use tokio::sync::watch;

pub use super::admission::RESERVE_CONNECTIONS;
use super::admission::{Admission, ConnectionContext, Ticket};
use super::body_limits::{Pace, PacedBody};
use super::connection_io::{Activity, ConnectionIo, MAX_HEAD_BYTES};
use crate::api::ServiceError;

/// HTTP connection handling and the cross-site guard (`http` in the config file).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HttpConfig {
    /// Connections served at once [default: min(4096, the process's file limit / 4)].
    pub max_connections: Option<usize>,
    /// Time to deliver a request head, from when the server starts waiting for one.
    pub header_timeout_ms: u64,
    /// A connection on which nothing moves this long, with no request being worked on, closes.
    pub idle_timeout_ms: u64,
    /// A request body must arrive at this many bytes per second on average, counted after a
    /// grace of `header_timeout_ms` (0: no minimum).
    pub body_min_bytes_per_s: u64,
    /// Host names (no port) accepted in `Host` besides the listen address's own and, on
    /// loopback, `localhost`, `127.0.0.1` and `[::1]` (see `transport::http_guard`).
    pub allowed_hosts: Vec<String>,
    /// Origins (`scheme://host[:port]`) allowed to send state-changing requests besides the
    /// server's own.
    pub allowed_origins: Vec<String>,
}

impl Default for HttpConfig {
    fn default() -> Self {
        Self {
            max_connections: None,
            header_timeout_ms: 10_000,
            idle_timeout_ms: 60_000,
            body_min_bytes_per_s: 1024,
            allowed_hosts: Vec::new(),
            allowed_origins: Vec::new(),
        }
    }
}

/// Header timeout of a reserve connection: a probe sends its request at once.
const RESERVE_HEADER_TIMEOUT: Duration = Duration::from_secs(1);
/// Never fewer connections than this, whatever the file limit says.
const MIN_CONNECTIONS: usize = 64;

/// Raises the soft limit on open files to the hard limit (sockets are files), and returns the
/// limit now in force (`None` when it cannot be read).
pub fn raise_file_limit() -> Option<u64> {
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit and setrlimit only read and write the struct passed in.
    unsafe {
        if libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) != 0 {
            return None;
        }
        if limit.rlim_cur < limit.rlim_max {
            let raised = libc::rlimit {
                rlim_cur: limit.rlim_max,
                rlim_max: limit.rlim_max,
            };
            if libc::setrlimit(libc::RLIMIT_NOFILE, &raised) == 0 {
                limit = raised;
            }
        }
    }
    // rlim_t is u64 on Linux, but not on every libc target.
    #[allow(clippy::unnecessary_cast)]
    Some(limit.rlim_cur as u64)
}

/// Pending connections the kernel may queue before the server accepts them. A burst beyond
/// the queue has its handshakes dropped, and each dropped client retries only after a second
/// (the initial SYN timeout): a health probe caught behind a burst of half-open connections
/// would take a second. The kernel caps this at `net.core.somaxconn`.
const ACCEPT_QUEUE: u32 = 4096;

/// Binds the HTTP listener on `address` (`host:port`; the first resolved address that binds)
/// with an accept queue of [`ACCEPT_QUEUE`] instead of the usual 1024.
pub async fn bind(address: &str) -> std::io::Result<TcpListener> {
    let mut last_error = None;
    for candidate in tokio::net::lookup_host(address).await? {
        let socket = match candidate {
            SocketAddr::V4(_) => tokio::net::TcpSocket::new_v4()?,
            SocketAddr::V6(_) => tokio::net::TcpSocket::new_v6()?,
        };
        // As std's and tokio's own bind: a restarted server may reuse a port in TIME_WAIT.
        socket.set_reuseaddr(true)?;
        match socket
            .bind(candidate)
            .and_then(|()| socket.listen(ACCEPT_QUEUE))
        {
            Ok(listener) => return Ok(listener),
            Err(e) => last_error = Some(e),
        }
    }
    Err(last_error.unwrap_or_else(|| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("{address} resolves to no address"),
        )
    }))
}

/// The connection cap: configured, or a quarter of the file limit (solves, the journal, zenoh
/// and the reserve need files too) and at most 4096.
pub fn connection_cap(config: &HttpConfig, file_limit: Option<u64>) -> usize {
    config.max_connections.unwrap_or_else(|| {
        let quarter = file_limit.map_or(4096, |l| (l / 4) as usize);
        quarter.clamp(MIN_CONNECTIONS, 4096)
    })
}

/// How one connection is served.
#[derive(Clone, Copy)]
struct Timeouts {
    header: Duration,
    idle: Duration,
    body_min_rate: u64,
}

/// Serves `app` on `listener` until `shutdown` resolves, then stops accepting, lets open
/// connections finish their requests and returns once they have all closed. With
/// `tokens_required`, connections that have not authenticated give way to newcomers at the cap.
pub async fn serve(
    listener: TcpListener,
    app: Router,
    config: &HttpConfig,
    cap: usize,
    tokens_required: bool,
    shutdown: impl Future<Output = ()> + Send,
) {
    let admission = Admission::new(cap, tokens_required);
    let timeouts = Timeouts {
        header: Duration::from_millis(config.header_timeout_ms.max(1)),
        idle: Duration::from_millis(config.idle_timeout_ms.max(1)),
        body_min_rate: config.body_min_bytes_per_s,
    };
    // Every connection task holds a receiver of `stopping`; `closed()` is when all are gone.
    let (stopping, stop_seen) = watch::channel(false);
    let mut shutdown = std::pin::pin!(shutdown);
    loop {
        let (stream, peer) = tokio::select! {
            () = &mut shutdown => break,
            accepted = listener.accept() => match accepted {
                Ok(accepted) => accepted,
                Err(e) => {
                    // Out of files or a connection reset before it was accepted: the cap keeps
                    // the first rare; pause so a persistent one does not spin.
                    tracing::warn!("accepting an HTTP connection: {e}");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
        };
        let _ = stream.set_nodelay(true);
        let stop_seen = stop_seen.clone();
        let Some(ticket) = admission.admit() else {
            tracing::debug!("{peer}: closed at once, {cap} connections and the reserve in use");
            continue;
        };
        let in_reserve = ticket.slot.is_none();
        let io = ConnectionIo::new(stream, Activity::new(), ticket.slot.clone());
        let timeouts = match in_reserve {
            false => timeouts,
            true => Timeouts {
                header: timeouts.header.min(RESERVE_HEADER_TIMEOUT),
                idle: timeouts.idle.min(RESERVE_HEADER_TIMEOUT),
                ..timeouts
            },
        };
        let connection = Connection {
            app: app.clone(),
            timeouts,
            ticket,
        };
        tokio::spawn(connection.run(io, stop_seen, peer));
    }
    tracing::info!("shutting down: no new connections");
    drop(listener);
    let _ = stopping.send(true);
    drop(stop_seen);
    stopping.closed().await;
}

struct Connection {
    app: Router,
    timeouts: Timeouts,
    /// Its place: the eviction notice, its standing, its slot (none in the reserve).
    ticket: Ticket,
}

impl Connection {
    async fn run(self, io: ConnectionIo, mut stop_seen: watch::Receiver<bool>, peer: SocketAddr) {
        let activity = io.activity();
        let Ticket {
            mut evicted,
            standing,
            slot,
        } = self.ticket;
        let in_reserve = slot.is_none();
        let context = ConnectionContext {
            peer,
            header_timeout: self.timeouts.header,
            standing,
        };
        let pace = Pace {
            min_rate: self.timeouts.body_min_rate,
            grace: self.timeouts.header,
            deadline: None,
            max_bytes: None,
        };
        let router = TowerToHyperService::new(self.app);
        let answering = Arc::clone(&activity);
        let service = hyper::service::service_fn(move |request: Request<Incoming>| {
            context.standing.request_arrived();
            let busy = answering.begin_answer();
            let refused = in_reserve && !is_probe(&request);
            let mut request = request.map(|body| Body::new(PacedBody::new(body, pace)));
            request.extensions_mut().insert(context.clone());
            let answer = (!refused).then(|| hyper::service::Service::call(&router, request));
            async move {
                let _busy = busy;
                match answer {
                    Some(answer) => answer.await,
                    None => Ok(too_many_connections()),
                }
            }
        });
        let mut builder = hyper::server::conn::http1::Builder::new();
        builder
            .timer(TokioTimer::new())
            .header_read_timeout(self.timeouts.header)
            .max_buf_size(MAX_HEAD_BYTES)
            // A reserve connection answers one probe and closes, freeing its place.
            .keep_alive(!in_reserve);
        let connection = builder
            .serve_connection(TokioIo::new(io), service)
            .with_upgrades();
        let mut connection = std::pin::pin!(connection);
        // Only a sent notice evicts; the accept loop also drops places it no longer tracks.
        let evicted = async {
            if (&mut evicted).await.is_err() {
                std::future::pending::<()>().await;
            }
        };
        let mut evicted = std::pin::pin!(evicted);
        let mut stopping = false;
        loop {
            tokio::select! {
                result = connection.as_mut() => {
                    if let Err(e) = result {
                        tracing::debug!("{peer}: connection ended: {e}");
                    }
                    break;
                }
                () = idle(&activity, self.timeouts.idle) => {
                    tracing::debug!("{peer}: closed after {:?} idle", self.timeouts.idle);
                    break;
                }
                () = &mut evicted => {
                    tracing::debug!("{peer}: place taken by a newer connection");
                    break;
                }
                changed = stop_seen.changed(), if !stopping => {
                    stopping = true;
                    if changed.is_ok() {
                        connection.as_mut().graceful_shutdown();
                    }
                }
            }
        }
    }
}

/// Resolves once nothing has moved on the connection for `limit` while no handler was
/// working on one of its requests.
async fn idle(activity: &Activity, limit: Duration) {
    loop {
        let quiet = activity.quiet_for();
        if quiet >= limit && !activity.answering() {
            return;
        }
        let wait = limit.saturating_sub(quiet).max(Duration::from_millis(100));
        tokio::time::sleep(wait).await;
    }
}

/// What a reserve connection may ask: liveness and metrics, nothing that takes work.
fn is_probe(request: &Request<Incoming>) -> bool {
    request.method() == Method::GET && matches!(request.uri().path(), "/v1/health" | "/metrics")
}

fn too_many_connections() -> Response {
    let error = ServiceError::unavailable(
        "too_many_connections",
        "the server is at its connection limit; only GET /v1/health and /metrics are answered",
        1,
    );
    let mut response = super::HttpError::from(error).into_response();
    response
        .headers_mut()
        .insert(header::CONNECTION, HeaderValue::from_static("close"));
    response
}
