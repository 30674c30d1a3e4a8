//! zenoh adapter: an in-process peer that maps key expressions onto [`Command`]s and publishes
//! every session's events.
//!
//! Key expressions (`<p>` is the prefix, `factord` by default; payloads are JSON, the messages
//! of `proto/v1/`):
//! - `<p>/rpc` — queryable: the payload is any [`Command`] (`{"op": "create_session", …}`); the
//!   reply is the command's answer, or an error reply with `{"error": {…}}`.
//! - `<p>/<session>/estimate` — queryable: the current estimate; selector parameters `since`,
//!   `from`, `to` as on HTTP.
//! - `<p>/<session>/in/batch` — subscriber: a [`Batch`](crate::api::wire::Batch) (robots publish here). Acknowledgements
//!   go to `out/acks`, rejections to `out/errors`.
//! - `<p>/<session>/in/optimize` — subscriber: solve now.
//! - `<p>/<session>/out/{acks,stats,poses,summary,errors}` — publications of the session events.
//! - `<p>/<session>/bin/poses` — the estimates of `out/poses` in binary (`proto/v1/poses-binary.md`,
//!   `crate::api::poses_binary`); a `lagged` marker there is JSON.
//! - `<p>/<session>/robot/<id>/{poses,odom_poses,bin/poses,bin/odom_poses,map_from_odom}` —
//!   a session with robots: each robot's own estimates (map and odometry frame) and frame, see
//!   `robot_streams`; queryables `<p>/<session>/robot/<id>/{estimate,map_from_odom}`, see
//!   `robot_queries`.
//!
//! In a fleet (`--fleet`, see `fleet.rs`) the same keys are served by the fleet as one: one
//! instance at a time declares `<p>/rpc` (the gateway, `gateway.rs`: a query must never reach
//! two instances), answering or forwarding to the session's owner, and the owner of a session
//! alone declares its `in/*`, `estimate` and `rpc` keys and publishes its `out/*`; membership
//! lives under `<p>/@fleet/`.

use std::sync::Arc;

use zenoh::bytes::ZBytes;
use zenoh::query::Query;

use crate::api::wire::EstimateQuery;
use crate::api::ErrorKind;
use crate::api::Reply;
use crate::service::{parse_query, Caller, Command, Recording, Service, ServiceError};

mod config;
mod fleet;
mod fleet_proof;
mod fleet_routes;
mod forward;
mod gateway;
mod heard;
mod inputs;
mod robot_queries;
mod robot_streams;

use config::{caller, config, zenoh_error};
pub use config::{ZenohConfig, ZenohError};
use forward::forward;

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
pub(super) fn oversized(
    payload: Option<&zenoh::bytes::ZBytes>,
    limit: usize,
) -> Option<ServiceError> {
    let len = payload.map_or(0, |p| p.len());
    (len > limit).then(|| {
        let message = format!("the payload has {len} bytes; the limit is {limit} (max_body_bytes)");
        ServiceError::new(ErrorKind::TooLarge, "body_too_large", message).at("payload")
    })
}

/// What every handler needs: the service, who zenoh peers are, the prefix, the size limit.
#[derive(Clone)]
pub(super) struct Context {
    pub(super) service: Arc<Service>,
    pub(super) caller: Arc<Caller>,
    pub(super) prefix: String,
    pub(super) max_payload: usize,
    pub(super) zenoh: zenoh::Session,
}

pub async fn start(
    service: Arc<Service>,
    cfg: &ZenohConfig,
    policy: ZenohPolicy,
) -> Result<ZenohAdapter, ZenohError> {
    let prefix = prefix(cfg);
    let mut config = config(cfg)?;
    if let Some(fleet) = service.fleet() {
        config::set_fleet_lease(&mut config, fleet.lease())?;
    }
    let caller = Arc::new(caller(&config, cfg, policy.tokens_required)?);
    let session = zenoh::open(config).await.map_err(zenoh_error)?;
    let ctx = Context {
        service: Arc::clone(&service),
        caller: Arc::clone(&caller),
        prefix: prefix.clone(),
        max_payload: policy.max_payload_bytes,
        zenoh: session.clone(),
    };
    let fleet = service.fleet().cloned();
    let mut tasks = Vec::new();

    match fleet {
        // Sessions' keys are declared by their owner only, as it loads them; `<p>/rpc` by one
        // instance at a time (`gateway`).
        Some(fleet) => tasks.extend(fleet::start(&ctx, fleet).await?),
        None => {
            let rpc = session
                .declare_queryable(format!("{prefix}/rpc"))
                .await
                .map_err(zenoh_error)?;
            let c = ctx.clone();
            tasks.push(tokio::spawn(async move {
                while let Ok(query) = rpc.recv_async().await {
                    let c = c.clone();
                    // Commands with `wait` may take a while: never block the queryable.
                    tokio::spawn(async move { answer_rpc(&c, &query).await });
                }
            }));
            let estimates = session
                .declare_queryable(format!("{prefix}/*/estimate"))
                .await
                .map_err(zenoh_error)?;
            let c = ctx.clone();
            tasks.push(tokio::spawn(async move {
                while let Ok(query) = estimates.recv_async().await {
                    answer_estimate(&c, &query).await;
                }
            }));
            tasks.extend(declare_robot_queries(&ctx, &format!("{prefix}/*")).await?);
            let inputs = session
                .declare_subscriber(format!("{prefix}/*/in/*"))
                .await
                .map_err(zenoh_error)?;
            tasks.extend(inputs::take_inputs(&ctx, inputs));
        }
    }

    // Forward every session's events, for the sessions that exist and those created later
    // (subscribed before the creation is acknowledged, so no event is missed); only those
    // zenoh peers may see: any peer can subscribe to what is published.
    let publisher = session.clone();
    let fwd_prefix = prefix.clone();
    let runtime = tokio::runtime::Handle::current();
    // Weak: the observer is kept by the service itself.
    let bound_service = Arc::downgrade(&service);
    let max_payload = policy.max_payload_bytes;
    service.observe_sessions(Box::new(move |s| {
        if caller.may_see(s) {
            let _guard = runtime.enter();
            forward(publisher.clone(), fwd_prefix.clone(), s);
            // A session with a ROS 2 binding joins the robots' ROS graph on this zenoh session.
            if let Some(service) = bound_service.upgrade() {
                let context = super::ros2::Context {
                    zenoh: publisher.clone(),
                    service,
                    caller: Arc::clone(&caller),
                    max_payload,
                };
                super::ros2::bind(context, s);
            }
        }
    }));
    tracing::info!("zenoh peer {} serving `{prefix}/**`", session.zid());
    Ok(ZenohAdapter { session, tasks })
}

/// The queryables of robots' keys under `sessions` (`<p>/*`, or one session's `<p>/<s>`),
/// see `robot_queries`.
pub(super) async fn declare_robot_queries(
    c: &Context,
    sessions: &str,
) -> Result<Vec<tokio::task::JoinHandle<()>>, ZenohError> {
    let estimates = c
        .zenoh
        .declare_queryable(format!("{sessions}/robot/*/estimate"))
        .await
        .map_err(zenoh_error)?;
    let frames = c
        .zenoh
        .declare_queryable(format!("{sessions}/robot/*/map_from_odom"))
        .await
        .map_err(zenoh_error)?;
    let (ctx, ctx2) = (c.clone(), c.clone());
    Ok(vec![
        tokio::spawn(async move {
            while let Ok(query) = estimates.recv_async().await {
                robot_queries::answer_robot_estimate(&ctx, &query).await;
            }
        }),
        tokio::spawn(async move {
            while let Ok(query) = frames.recv_async().await {
                robot_queries::answer_robot_frame(&ctx2, &query).await;
            }
        }),
    ])
}

/// `<p>/rpc` outside a fleet: any command, run here.
pub(super) async fn answer_rpc(c: &Context, query: &Query) {
    rpc_answer(c, query).await.send(query).await;
}

/// The answer to the command in `query`, run here.
pub(super) async fn rpc_answer(c: &Context, query: &Query) -> Answer {
    let max_items = c.service.limits().max_batch_items;
    let result = match oversized(query.payload(), c.max_payload) {
        Some(refusal) => Err(refusal),
        None => match crate::service::parse_command(&payload(query), max_items) {
            Ok(command) => {
                c.service
                    .execute(&c.caller, command, Recording::History)
                    .await
            }
            Err(e) => Err(e),
        },
    };
    Answer::of(result.map(|r| serde_json::to_vec(&r)))
}

/// `<p>/<session>/estimate`.
pub(super) async fn answer_estimate(c: &Context, query: &Query) {
    answer_estimate_command(c, query, estimate_command(query)).await;
}

/// Runs an estimate read (the session's or a robot's) and replies with it: a file format as its
/// text, as over HTTP; the JSON estimate as JSON.
pub(super) async fn answer_estimate_command(
    c: &Context,
    query: &Query,
    command: Result<Command, ServiceError>,
) {
    let result = match command {
        Ok(command) => {
            c.service
                .execute(&c.caller, command, Recording::History)
                .await
        }
        Err(e) => Err(e),
    };
    reply(
        query,
        result.map(|r| match r {
            Reply::Export(file) => Ok(file.body.into_bytes()),
            r => serde_json::to_vec(&r),
        }),
    )
    .await;
}

pub(super) fn payload(query: &Query) -> Vec<u8> {
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
    let estimate: EstimateQuery = parse_query(query.parameters().as_str())?;
    Ok(Command::get_estimate(name.into(), estimate))
}

pub(super) async fn reply(
    query: &Query,
    result: Result<serde_json::Result<Vec<u8>>, ServiceError>,
) {
    Answer::of(result).send(query).await;
}

/// A command's answer as zenoh carries it: a reply's payload, or an error reply's
/// (`{"error": {…}}`).
#[must_use = "an answer must be sent, or the query gets no reply"]
pub(super) enum Answer {
    Reply(ZBytes),
    Error(ZBytes),
}

impl Answer {
    pub(super) fn of(result: Result<serde_json::Result<Vec<u8>>, ServiceError>) -> Self {
        match result {
            Ok(Ok(body)) => Answer::Reply(body.into()),
            Ok(Err(e)) => Answer::error(ServiceError::internal(e.to_string())),
            Err(e) => {
                crate::runtime::metrics::count_rejection(&e.body);
                Answer::error(e)
            }
        }
    }

    pub(super) fn error(e: ServiceError) -> Self {
        Answer::Error(serde_json::json!({ "error": e.body }).to_string().into())
    }

    /// Sends it as the answer to `query`.
    pub(super) async fn send(self, query: &Query) {
        let outcome = match self {
            Answer::Reply(body) => query.reply(query.key_expr().clone(), body).await,
            Answer::Error(body) => query.reply_err(body).await,
        };
        if let Err(e) = outcome {
            tracing::warn!("zenoh reply failed: {e}");
        }
    }
}
