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

use std::collections::HashSet;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use zenoh::sample::SampleKind;

use super::config::zenoh_error;
use super::fleet_proof;
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
            let key = ctx.service.fleet().and_then(|f| f.key());
            let proof = fleet_proof::sign_info(key, &query, &info_key, &body);
            if let Err(e) = query.reply(&info_key, body).attachment(proof).await {
                tracing::warn!("zenoh reply failed: {e}");
            }
        }
    }));

    let rpc = z
        .declare_queryable(format!("{prefix}/@fleet/{me}/rpc"))
        .complete(true)
        .await
        .map_err(zenoh_error)?;
    let (ctx, forwarded_to) = (c.clone(), Arc::clone(&fleet));
    tasks.push(tokio::spawn(async move {
        while let Ok(query) = rpc.recv_async().await {
            let (ctx, fleet) = (ctx.clone(), Arc::clone(&forwarded_to));
            tokio::spawn(async move { answer_forwarded(&ctx, &fleet, &query).await });
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
    let announced = Announced::default();
    tasks.push(tokio::spawn(async move {
        let _token = token;
        while let Ok(sample) = members.recv_async().await {
            let Some(id) = sample.key_expr().as_str().rsplit('/').next() else {
                continue;
            };
            match sample.kind() {
                SampleKind::Put => {
                    announced.set(id, true);
                    // On a trusted network an announcement is membership; with a secret,
                    // only the proof in its `info` answer is (`learn_url`).
                    if watched.key().is_none() {
                        watched.member_up(id, Member::default());
                    }
                    let (ctx, fleet, id) = (ctx.clone(), Arc::clone(&watched), id.to_string());
                    let announced = announced.clone();
                    tokio::spawn(async move { learn_url(&ctx, &fleet, &announced, &id).await });
                }
                SampleKind::Delete => {
                    announced.set(id, false);
                    watched.member_down(id)
                }
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

/// The ids whose liveliness token `<p>/@fleet/<id>` is alive now.
#[derive(Clone, Default)]
struct Announced(Arc<Mutex<HashSet<String>>>);

impl Announced {
    fn set(&self, id: &str, alive: bool) {
        let mut ids = self.0.lock().unwrap_or_else(|p| p.into_inner());
        match alive {
            true => ids.insert(id.to_string()),
            false => ids.remove(id),
        };
    }

    fn alive(&self, id: &str) -> bool {
        self.0
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .contains(id)
    }
}

/// Asks instance `id` for its `info` until it answers with a valid proof (or leaves), then
/// records it as a member with its HTTP URL.
async fn learn_url(c: &Context, fleet: &Fleet, announced: &Announced, id: &str) {
    if id == fleet.instance() {
        return;
    }
    for _ in 0..10 {
        if let Some(info) = info_of(c, id).await {
            if announced.alive(id) {
                fleet.member_up(
                    id,
                    Member {
                        http: Some(info.http),
                    },
                );
            }
            return;
        }
        if !announced.alive(id) {
            return;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    match fleet.key() {
        Some(_) => tracing::warn!(
            instance = id,
            "fleet: `{id}` announced itself but gave no info with a valid fleet proof: not \
             taken into the fleet (another fleet's secret, or not an instance)"
        ),
        None => tracing::warn!(
            instance = id,
            "fleet: the instance does not answer its info query"
        ),
    }
}

/// Instance `id`'s `info`, or every live instance's with `id` = `*`: those that prove
/// membership (see `fleet_proof`).
pub(super) async fn infos(c: &Context, id: &str) -> Vec<FleetInfo> {
    let key = c.service.fleet().and_then(|f| f.key());
    let (selector, nonce) = fleet_proof::info_selector(&c.prefix, id, key);
    let get = c
        .zenoh
        .get(selector)
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
            out.extend(fleet_proof::verified_info(key, nonce.as_deref(), sample));
        }
    }
    out
}

/// A command another member forwarded here: run here (never forwarded again) once its proof
/// holds, the answer sealed for the forwarder.
async fn answer_forwarded(c: &Context, fleet: &Fleet, query: &zenoh::query::Query) {
    let key = fleet.key();
    match fleet_proof::accept_rpc(key, fleet.instance(), query) {
        Ok(stamp) => {
            let answer = fleet_routes::route_rpc(c, query, Forward::No).await;
            fleet_proof::send_sealed(key, stamp.as_ref(), query, answer).await;
        }
        Err(refusal) => super::Answer::of(Err(refusal)).send(query).await,
    }
}

async fn info_of(c: &Context, id: &str) -> Option<FleetInfo> {
    infos(c, id).await.into_iter().find(|i| i.instance == id)
}
