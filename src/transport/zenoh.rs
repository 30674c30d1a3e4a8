//! zenoh adapter: an in-process peer that maps key expressions onto [`Command`]s and publishes
//! every session's events.
//!
//! Key expressions (`<p>` is the prefix, `factord` by default; payloads are JSON, the messages
//! of `proto/v1/`):
//! - `<p>/rpc` — queryable: the payload is any [`Command`] (`{"op": "create_session", …}`); the
//!   reply is the command's answer, or an error reply with `{"error": {…}}`.
//! - `<p>/<session>/estimate` — queryable: the current estimate; selector parameters `since`,
//!   `from`, `to` as on HTTP.
//! - `<p>/<session>/in/batch` — subscriber: a [`Batch`] (robots publish here). Acknowledgements
//!   go to `out/acks`, rejections to `out/errors`.
//! - `<p>/<session>/in/optimize` — subscriber: solve now.
//! - `<p>/<session>/out/{acks,stats,poses,summary,errors}` — publications of the session events.

use std::sync::Arc;

use zenoh::qos::CongestionControl;
use zenoh::query::Query;

use crate::api::wire::{EstimateQuery, SessionEvent};
use crate::api::ErrorKind;
use crate::service::{parse_query, Caller, Command, Service, ServiceError};

#[derive(Clone, Debug, Default, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ZenohConfig {
    /// Endpoints to listen on, e.g. `tcp/0.0.0.0:7447`.
    pub listen: Vec<String>,
    /// Routers or peers to connect to.
    pub connect: Vec<String>,
    /// Multicast scouting for other peers on the LAN.
    pub multicast: bool,
    /// First chunk of every key expression.
    pub prefix: String,
    /// A zenoh JSON5 configuration to start from (access control, TLS, authentication: see
    /// `docker/zenoh-secure.json5`); the settings above are applied on top of it.
    pub config_file: Option<std::path::PathBuf>,
    /// The principal (a token label, as in the tokens file) that every zenoh peer acts as: it
    /// reaches the sessions that label owns, and owns the sessions it creates. Only with
    /// zenoh's own authentication in `config_file` (user/password, or mutual TLS on every
    /// endpoint): zenoh then decides who is a peer at all, and its ACL what each may do.
    /// Without it, and with HTTP tokens on, zenoh peers are anonymous: they reach only unowned
    /// sessions (see `service::caller`).
    pub principal: Option<String>,
}

#[derive(Debug, thiserror::Error)]
pub enum ZenohError {
    #[error("zenoh configuration `{key}`: {message}")]
    Config { key: String, message: String },
    #[error("zenoh: {0}")]
    Zenoh(String),
}

fn zenoh_error(e: impl std::fmt::Display) -> ZenohError {
    ZenohError::Zenoh(e.to_string())
}

fn config(cfg: &ZenohConfig) -> Result<zenoh::Config, ZenohError> {
    let mut config = match &cfg.config_file {
        Some(path) => zenoh::Config::from_file(path).map_err(|e| ZenohError::Config {
            key: path.display().to_string(),
            message: e.to_string(),
        })?,
        None => zenoh::Config::default(),
    };
    let json = |v: &Vec<String>| serde_json::to_string(v).expect("strings serialise");
    for (key, value) in [
        ("mode", "\"peer\"".to_string()),
        ("scouting/multicast/enabled", cfg.multicast.to_string()),
        ("scouting/gossip/enabled", "true".to_string()),
        ("listen/endpoints", json(&cfg.listen)),
        ("connect/endpoints", json(&cfg.connect)),
    ] {
        config
            .insert_json5(key, &value)
            .map_err(|e| ZenohError::Config {
                key: key.into(),
                message: e.to_string(),
            })?;
    }
    Ok(config)
}

/// Whether zenoh authenticates every peer before it may send anything: user/password on every
/// link, or mutual TLS with only TLS endpoints (a plain `tcp/` endpoint beside it is open).
fn authenticated(config: &zenoh::Config, cfg: &ZenohConfig) -> bool {
    let set = |key: &str| {
        config
            .get_json(key)
            .is_ok_and(|v| v != "null" && v != "false" && v != "\"\"")
    };
    let usrpwd = set("transport/auth/usrpwd/dictionary_file");
    let mtls = set("transport/link/tls/enable_mtls")
        && !cfg.listen.is_empty()
        && cfg
            .listen
            .iter()
            .chain(&cfg.connect)
            .all(|e| e.starts_with("tls/"));
    usrpwd || mtls
}

/// Who zenoh peers are: see [`ZenohConfig::principal`]. With HTTP tokens on and zenoh open,
/// peers are anonymous, and the operator is told so.
fn caller(
    config: &zenoh::Config,
    cfg: &ZenohConfig,
    tokens_required: bool,
) -> Result<Caller, ZenohError> {
    match (&cfg.principal, authenticated(config, cfg)) {
        (Some(label), true) => Ok(Caller::Principal(label.as_str().into())),
        (Some(_), false) => Err(ZenohError::Config {
            key: "zenoh.principal".into(),
            message: "needs zenoh's own authentication in zenoh.config_file \
                      (transport/auth/usrpwd/dictionary_file, or transport/link/tls/enable_mtls \
                      with only tls/ endpoints): otherwise any peer would act as that principal"
                .into(),
        }),
        (None, _) if tokens_required => {
            tracing::warn!(
                "HTTP requires bearer tokens but zenoh peers are anonymous: any zenoh peer can \
                 create, read, write and delete the sessions created over zenoh, and sessions \
                 created with a token are invisible over zenoh (404, not published). Secure \
                 zenoh (user/password or mutual TLS) and set zenoh.principal to reach them"
            );
            Ok(Caller::Anonymous)
        }
        (None, _) => Ok(Caller::Trusted),
    }
}

/// The running adapter; dropping it does not close the session, [`ZenohAdapter::close`] does.
pub struct ZenohAdapter {
    session: zenoh::Session,
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

impl ZenohAdapter {
    pub async fn close(self) {
        for t in &self.tasks {
            t.abort();
        }
        let _ = self.session.close().await;
    }
}

fn prefix(cfg: &ZenohConfig) -> String {
    if cfg.prefix.is_empty() {
        "factord".into()
    } else {
        cfg.prefix.trim_end_matches('/').into()
    }
}

/// What the rest of the server's configuration decides for zenoh.
#[derive(Clone, Copy, Debug)]
pub struct ZenohPolicy {
    /// HTTP requires bearer tokens: decides who zenoh peers are ([`ZenohConfig::principal`]).
    pub tokens_required: bool,
    /// The largest rpc or put payload, as HTTP's `max_body_bytes`: 413 `body_too_large`.
    pub max_payload_bytes: usize,
}

/// The size refusal of a payload beyond the limit, before it is copied or decoded.
fn oversized(payload: Option<&zenoh::bytes::ZBytes>, limit: usize) -> Option<ServiceError> {
    let len = payload.map_or(0, |p| p.len());
    (len > limit).then(|| {
        let message = format!("the payload has {len} bytes; the limit is {limit} (max_body_bytes)");
        ServiceError::new(ErrorKind::TooLarge, "body_too_large", message).at("payload")
    })
}

pub async fn start(
    service: Arc<Service>,
    cfg: &ZenohConfig,
    policy: ZenohPolicy,
) -> Result<ZenohAdapter, ZenohError> {
    let prefix = prefix(cfg);
    let config = config(cfg)?;
    let caller = Arc::new(caller(&config, cfg, policy.tokens_required)?);
    let max_payload = policy.max_payload_bytes;
    let session = zenoh::open(config).await.map_err(zenoh_error)?;
    let mut tasks = Vec::new();

    let rpc = session
        .declare_queryable(format!("{prefix}/rpc"))
        .await
        .map_err(zenoh_error)?;
    let svc = Arc::clone(&service);
    let who = Arc::clone(&caller);
    tasks.push(tokio::spawn(async move {
        while let Ok(query) = rpc.recv_async().await {
            let (svc, who) = (Arc::clone(&svc), Arc::clone(&who));
            // Commands with `wait` may take a while: never block the queryable.
            tokio::spawn(async move {
                let max_items = svc.limits().max_batch_items;
                let result = match oversized(query.payload(), max_payload) {
                    Some(refusal) => Err(refusal),
                    None => match crate::service::parse_command(&payload(&query), max_items) {
                        Ok(command) => svc.execute_as(&who, command).await,
                        Err(e) => Err(e),
                    },
                };
                reply(&query, result.map(|r| serde_json::to_vec(&r))).await;
            });
        }
    }));

    let estimates = session
        .declare_queryable(format!("{prefix}/*/estimate"))
        .await
        .map_err(zenoh_error)?;
    let svc = Arc::clone(&service);
    let who = Arc::clone(&caller);
    tasks.push(tokio::spawn(async move {
        while let Ok(query) = estimates.recv_async().await {
            let result = estimate_command(&query).map(|c| async { svc.execute_as(&who, c).await });
            let result = match result {
                Ok(fut) => fut.await,
                Err(e) => Err(e),
            };
            reply(&query, result.map(|r| serde_json::to_vec(&r))).await;
        }
    }));

    let inputs = session
        .declare_subscriber(format!("{prefix}/*/in/*"))
        .await
        .map_err(zenoh_error)?;
    let svc = Arc::clone(&service);
    let who = Arc::clone(&caller);
    let publisher = session.clone();
    let in_prefix = prefix.clone();
    tasks.push(tokio::spawn(async move {
        while let Ok(sample) = inputs.recv_async().await {
            let key = sample.key_expr().as_str().to_string();
            let mut parts = key[in_prefix.len() + 1..].split('/');
            let (Some(name), Some("in"), Some(what)) = (parts.next(), parts.next(), parts.next())
            else {
                continue;
            };
            // Puts have no reply: rejections go to the session's stream (SSE and `out/errors`),
            // or straight to `out/errors` when there is no such session or the put is too
            // large to read (that refusal tells the sender nothing of the session).
            let outcome = match oversized(Some(sample.payload()), max_payload) {
                Some(refusal) => Err(refusal),
                None => {
                    let bytes = sample.payload().to_bytes();
                    svc.deliver(&who, name, what, &bytes).await
                }
            };
            if let Err(error) = outcome {
                let event = SessionEvent::Error {
                    session: name.into(),
                    sequence: None,
                    error: error.body,
                };
                let body = serde_json::to_vec(&event).expect("events serialise");
                let _ = publisher
                    .put(format!("{in_prefix}/{name}/out/errors"), body)
                    .await;
            }
        }
    }));

    // Forward every session's events, for the sessions that exist and those created later
    // (subscribed before the creation is acknowledged, so no event is missed); only those
    // zenoh peers may see: any peer can subscribe to what is published.
    let publisher = session.clone();
    let fwd_prefix = prefix.clone();
    let runtime = tokio::runtime::Handle::current();
    service.observe_sessions(Box::new(move |s| {
        if caller.may_see(s) {
            let _guard = runtime.enter();
            forward(publisher.clone(), fwd_prefix.clone(), s);
        }
    }));
    tracing::info!("zenoh peer {} serving `{prefix}/**`", session.zid());
    Ok(ZenohAdapter { session, tasks })
}

/// Publishes a session's events until it is deleted (its event channel closes).
fn forward(zenoh: zenoh::Session, prefix: String, session: &Arc<crate::session::Session>) {
    let mut rx = session.subscribe();
    let name = session.name.clone();
    tokio::spawn(async move {
        loop {
            let event = match rx.recv().await {
                Ok(event) => event,
                Err(tokio::sync::broadcast::error::RecvError::Lagged(n)) => {
                    tracing::warn!("zenoh publisher of session {name} skipped {n} events");
                    continue;
                }
                Err(_) => return,
            };
            let body = serde_json::to_vec(&*event).expect("events serialise");
            let key = format!("{prefix}/{name}/out/{}", event.topic());
            // Iteration statistics may be dropped under congestion; estimates and the rest not.
            let congestion = match *event {
                SessionEvent::Iteration { .. } => CongestionControl::Drop,
                _ => CongestionControl::Block,
            };
            if let Err(e) = zenoh.put(key, body).congestion_control(congestion).await {
                tracing::warn!("zenoh publication for session {name} failed: {e}");
            }
        }
    });
}

fn payload(query: &Query) -> Vec<u8> {
    query
        .payload()
        .map(|p| p.to_bytes().to_vec())
        .unwrap_or_default()
}

fn estimate_command(query: &Query) -> Result<Command, ServiceError> {
    let key = query.key_expr().as_str();
    let name = key.rsplit('/').nth(1).ok_or_else(|| {
        ServiceError::bad_request("invalid_key", "key", "expected <prefix>/<session>/estimate")
    })?;
    let EstimateQuery { since, from, to } = parse_query(query.parameters().as_str())?;
    Ok(Command::GetEstimate {
        session: name.into(),
        since,
        from,
        to,
    })
}

async fn reply(query: &Query, result: Result<serde_json::Result<Vec<u8>>, ServiceError>) {
    let outcome = match result {
        Ok(Ok(body)) => query.reply(query.key_expr().clone(), body).await,
        Ok(Err(e)) => {
            let body = serde_json::json!({ "error": ServiceError::internal(e.to_string()).body });
            query.reply_err(body.to_string()).await
        }
        Err(e) => {
            crate::runtime::metrics::count_rejection(&e.body);
            let body = serde_json::json!({ "error": e.body });
            query.reply_err(body.to_string()).await
        }
    };
    if let Err(e) = outcome {
        tracing::warn!("zenoh reply failed: {e}");
    }
}
