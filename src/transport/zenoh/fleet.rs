//! A fleet's membership over zenoh. Every instance
//! - declares the liveliness token `<p>/@fleet/<instance>` (zenoh withdraws it when the
//!   instance's links close: a `kill -9` included);
//! - subscribes to the liveliness of `<p>/@fleet/*`, with history, to keep the live set
//!   ([`Fleet::member_up`], [`Fleet::member_down`]); each newcomer's `info` tells its HTTP URL;
//! - answers `<p>/@fleet/<instance>/info` ([`crate::service::fleet::FleetInfo`]: id, HTTP URL,
//!   sessions, load) and `<p>/@fleet/<instance>/rpc`, commands other instances forward to it
//!   (run here, never forwarded again);
//! - declares the keys of the sessions it holds, as it loads and releases them
//!   (`fleet_routes`);
//! - once settled, takes part in electing the one instance that serves `<p>/rpc` (`gateway`).
//!
//! `@fleet` is a verbatim chunk: `<p>/*/…` wildcards never match it, so it cannot be a session.

use std::sync::Arc;
use std::time::Duration;

use zenoh::sample::SampleKind;

use super::config::zenoh_error;
use super::fleet_routes::{self, Forward};
use super::{Context, ZenohError};
use crate::service::fleet::{Fleet, FleetInfo, Member};

/// How long a starting instance listens for the others before placing sessions: the
/// liveliness history and the peers' links arrive within it.
const SETTLE: Duration = Duration::from_millis(800);
/// How long an instance's `info` may take.
const INFO_TIMEOUT: Duration = Duration::from_secs(2);

pub(super) async fn start(
    c: &Context,
    fleet: Arc<Fleet>,
) -> Result<Vec<tokio::task::JoinHandle<()>>, ZenohError> {
    let (z, prefix, me) = (&c.zenoh, &c.prefix, fleet.instance().to_string());
    let mut tasks = Vec::new();

    let info_key = format!("{prefix}/@fleet/{me}/info");
    let info = z
        .declare_queryable(&info_key)
        .complete(true)
        .await
        .map_err(zenoh_error)?;
    let ctx = c.clone();
    tasks.push(tokio::spawn(async move {
        while let Ok(query) = info.recv_async().await {
            let Some(answer) = ctx.service.fleet_info(&ctx.caller) else {
                continue;
            };
            // Under this instance's own key: the query's may be `<p>/@fleet/*/info`.
            let body = serde_json::to_vec(&answer).expect("info serialises");
            if let Err(e) = query.reply(&info_key, body).await {
                tracing::warn!("zenoh reply failed: {e}");
            }
        }
    }));

    let rpc = z
        .declare_queryable(format!("{prefix}/@fleet/{me}/rpc"))
        .complete(true)
        .await
        .map_err(zenoh_error)?;
    let ctx = c.clone();
    tasks.push(tokio::spawn(async move {
        while let Ok(query) = rpc.recv_async().await {
            let ctx = ctx.clone();
            tokio::spawn(async move { fleet_routes::route_rpc(&ctx, &query, Forward::No).await });
        }
    }));

    tasks.push(fleet_routes::start(c, Arc::clone(&fleet)));

    let token = z
        .liveliness()
        .declare_token(format!("{prefix}/@fleet/{me}"))
        .await
        .map_err(zenoh_error)?;
    let members = z
        .liveliness()
        .declare_subscriber(format!("{prefix}/@fleet/*"))
        .history(true)
        .await
        .map_err(zenoh_error)?;
    let ctx = c.clone();
    let watched = Arc::clone(&fleet);
    tasks.push(tokio::spawn(async move {
        let _token = token;
        while let Ok(sample) = members.recv_async().await {
            let Some(id) = sample.key_expr().as_str().rsplit('/').next() else {
                continue;
            };
            match sample.kind() {
                SampleKind::Put => {
                    watched.member_up(id, Member::default());
                    let (ctx, fleet, id) = (ctx.clone(), Arc::clone(&watched), id.to_string());
                    tokio::spawn(async move { learn_url(&ctx, &fleet, &id).await });
                }
                SampleKind::Delete => watched.member_down(id),
            }
        }
    }));
    let ctx = c.clone();
    tasks.push(tokio::spawn(async move {
        tokio::time::sleep(SETTLE).await;
        tracing::info!(live = ?fleet.live(), "fleet: membership settled");
        fleet.set_settled();
        if let Err(e) = super::gateway::run(ctx, fleet).await {
            tracing::error!("fleet: the rpc gateway election stopped: {e}");
        }
    }));
    Ok(tasks)
}

/// Asks instance `id` for its `info` until it answers (or leaves) and records its HTTP URL.
async fn learn_url(c: &Context, fleet: &Fleet, id: &str) {
    if id == fleet.instance() {
        return;
    }
    for _ in 0..10 {
        if let Some(info) = info_of(c, id).await {
            if fleet.member(id).is_some() {
                fleet.member_up(
                    id,
                    Member {
                        http: Some(info.http),
                    },
                );
            }
            return;
        }
        if fleet.member(id).is_none() {
            return;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    tracing::warn!(
        instance = id,
        "fleet: the instance does not answer its info query"
    );
}

/// Instance `id`'s `info`, or every live instance's with `id` = `*`.
pub(super) async fn infos(c: &Context, id: &str) -> Vec<FleetInfo> {
    let get = c
        .zenoh
        .get(format!("{}/@fleet/{id}/info", c.prefix))
        .target(zenoh::query::QueryTarget::All)
        .consolidation(zenoh::query::ConsolidationMode::None)
        .timeout(INFO_TIMEOUT)
        .await;
    let Ok(replies) = get else {
        return Vec::new();
    };
    let mut out = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result() {
            if let Ok(info) = serde_json::from_slice::<FleetInfo>(&sample.payload().to_bytes()) {
                out.push(info);
            }
        }
    }
    out
}

async fn info_of(c: &Context, id: &str) -> Option<FleetInfo> {
    infos(c, id).await.into_iter().find(|i| i.instance == id)
}
