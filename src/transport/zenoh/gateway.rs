//! The fleet's rpc gateway: one instance at a time declares `<p>/rpc`.
//!
//! Why not every instance: zenoh delivers a query to every matching queryable it does not rule
//! out, and which ones it rules out depends on the topology. Declared complete on all three
//! instances of a fleet, `<p>/rpc` was reached once from a peer, but twice from a zenoh client
//! connected to one of them (zenoh 1.10's peer routing sends a client's query to the local
//! queryable and to the other peers' alike): a creation answered 409 and success, a batch was
//! applied twice. Nothing in a query tells two deliveries of it apart, so the only way to run
//! each command once in every topology is to have one queryable on the key.
//!
//! Election, evaluated on every membership change and on a tick:
//! - an instance declares the liveliness token `<p>/@fleet/<id>/ready` once it has settled
//!   (learnt the membership), so an instance just starting is never elected before it serves;
//! - the elected one is the smallest ready id among the members (with a fleet secret, those
//!   that proved membership: a rogue peer's tokens neither take nor block the gateway); it
//!   declares `<p>/rpc` only when no other
//!   instance holds the token `<p>/@fleet/<id>/gateway` and it holds the gateway lock
//!   ([`Fleet::gateway_lock`], an OS lock on the shared state directory), then declares its own
//!   gateway token;
//! - an instance no longer elected undeclares `<p>/rpc` first, then its gateway token, then
//!   releases the lock: its successor starts serving only after seeing the token go, so no
//!   query can be answered by both. A gateway that dies loses its tokens with its links (and
//!   the kernel drops its lock): the next ready instance takes over within milliseconds on a
//!   `kill -9`. A host that stops answering (SIGSTOP, frozen) loses its tokens after zenoh's
//!   lease (`--fleet-lease-ms`) but keeps its lock: the elected successor takes the gateway
//!   over once that instance's heartbeat has stopped as long ([`Fleet::gateway_lock`]), by
//!   claiming the gateway's next ownership epoch.
//!
//! Why a resumed gateway cannot run a command twice: it checks its epoch before every command
//! and on every tick, and answers nothing once the epoch is over (it then withdraws `<p>/rpc`).
//! A query reaches two queryables only when both are declared when it is routed, so one that
//! the successor also received reaches the old gateway after the successor's claim: the check
//! drops it there. A command the old gateway had started before it stopped was never sent to
//! the successor; and a write it then runs on a session, here or forwarded, goes through that
//! session's own epoch fence (`journal::takeover`).
//!
//! The gateway answers as every instance used to (`fleet_routes::route_rpc`): commands without
//! a session itself, a session's command where the session lives. While no instance serves
//! (a handover, a fleet still settling) a query gets no reply at all, and nothing ran: callers
//! retry.

use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::{Duration, Instant};

use zenoh::liveliness::LivelinessToken;
use zenoh::query::Queryable;
use zenoh::sample::{Sample, SampleKind};

use super::fleet_routes::{self, Forward};
use super::{Context, ZenohError};
use crate::service::fleet::{Fleet, GatewayLock, LockError};

/// How often the election is evaluated besides on membership changes: retries a lock still
/// held by a predecessor stepping down.
const TICK: Duration = Duration::from_millis(200);
/// How long an elected instance may wait for the lock before it warns.
const LOCK_WARNING: Duration = Duration::from_secs(5);

/// Serving `<p>/rpc`: undeclared in [`Serving::stop`] in the order the module describes.
struct Serving {
    queryable: Queryable<()>,
    token: LivelinessToken,
    lock: GatewayLock,
}

impl Serving {
    async fn start(c: &Context, me: &str, lock: GatewayLock) -> Result<Self, ZenohError> {
        let p = &c.prefix;
        let runtime = tokio::runtime::Handle::current();
        let ctx = c.clone();
        let fence = lock.fence();
        let queryable = c
            .zenoh
            .declare_queryable(format!("{p}/rpc"))
            .complete(true)
            .callback(move |query| {
                // Taken over while this instance was stopped: no reply, nothing run (the
                // caller retries and reaches the successor).
                if fence.superseded() {
                    return;
                }
                let ctx = ctx.clone();
                // Commands with `wait` may take a while: never hold zenoh's thread.
                runtime.spawn(async move {
                    let answer = fleet_routes::route_rpc(&ctx, &query, Forward::Yes).await;
                    answer.send(&query).await
                });
            })
            .await
            .map_err(super::config::zenoh_error)?;
        let token = c
            .zenoh
            .liveliness()
            .declare_token(format!("{p}/@fleet/{me}/gateway"))
            .await
            .map_err(super::config::zenoh_error)?;
        Ok(Self {
            queryable,
            token,
            lock,
        })
    }

    async fn stop(self) {
        if let Err(e) = self.queryable.undeclare().await {
            tracing::warn!("fleet: undeclaring the rpc gateway's queryable: {e}");
        }
        if let Err(e) = self.token.undeclare().await {
            tracing::warn!("fleet: undeclaring the rpc gateway's token: {e}");
        }
    }
}

/// The ids behind the liveliness tokens `<p>/@fleet/<id>/<what>` alive now, as samples of a
/// subscriber to `<p>/@fleet/*/<what>` arrive.
#[derive(Default)]
struct Holders(BTreeSet<String>);

impl Holders {
    fn apply(&mut self, sample: &Sample) {
        let mut chunks = sample.key_expr().as_str().rsplit('/');
        let Some(id) = chunks.nth(1) else {
            return;
        };
        match sample.kind() {
            SampleKind::Put => self.0.insert(id.to_string()),
            SampleKind::Delete => self.0.remove(id),
        };
    }
}

impl Holders {
    /// Those of the fleet's members (itself included): a token from a peer that has not
    /// proved membership (`fleet_proof`) neither takes nor blocks the gateway.
    fn members(&self, fleet: &Fleet) -> Holders {
        let me = fleet.instance();
        let ids = self
            .0
            .iter()
            .filter(|id| *id == me || fleet.member(id).is_some());
        Holders(ids.cloned().collect())
    }
}

/// Whether `me` should serve: the smallest of the ready instances.
fn elected(ready: &Holders, me: &str) -> bool {
    ready.0.first().is_none_or(|first| first == me)
}

/// Runs the election for this settled instance until the adapter closes.
pub(super) async fn run(c: Context, fleet: Arc<Fleet>) -> Result<(), ZenohError> {
    let (z, p, me) = (&c.zenoh, &c.prefix, fleet.instance().to_string());
    let liveliness = |what: &str| {
        z.liveliness()
            .declare_subscriber(format!("{p}/@fleet/*/{what}"))
            .history(true)
    };
    let ready_tokens = liveliness("ready")
        .await
        .map_err(super::config::zenoh_error)?;
    let gateway_tokens = liveliness("gateway")
        .await
        .map_err(super::config::zenoh_error)?;
    let _ready = z
        .liveliness()
        .declare_token(format!("{p}/@fleet/{me}/ready"))
        .await
        .map_err(super::config::zenoh_error)?;
    let (mut ready, mut gateways) = (Holders::default(), Holders::default());
    ready.0.insert(me.clone());
    let mut serving: Option<Serving> = None;
    let mut waiting_since: Option<Instant> = None;
    let mut tick = tokio::time::interval(TICK);
    loop {
        tokio::select! {
            sample = ready_tokens.recv_async() => match sample {
                Ok(sample) => ready.apply(&sample),
                Err(_) => break,
            },
            sample = gateway_tokens.recv_async() => match sample {
                Ok(sample) => gateways.apply(&sample),
                Err(_) => break,
            },
            _ = tick.tick() => {}
        }
        ready.0.insert(me.clone());
        if serving
            .as_ref()
            .is_some_and(|s| s.lock.fence().superseded())
        {
            if let Some(s) = serving.take() {
                s.stop().await;
            }
            fleet.set_rpc_gateway(false);
            tracing::warn!(
                instance = me,
                "fleet: another instance took the rpc gateway over while this one was stopped"
            );
        }
        let elect = elected(&ready.members(&fleet), &me);
        if !elect {
            waiting_since = None;
            if let Some(s) = serving.take() {
                s.stop().await;
                fleet.set_rpc_gateway(false);
                tracing::info!(instance = me, "fleet: no longer the rpc gateway");
            }
            continue;
        }
        let others_serve = gateways.members(&fleet).0.iter().any(|g| *g != me);
        if serving.is_some() || others_serve {
            continue;
        }
        match fleet.gateway_lock() {
            Ok(lock) => {
                serving = Some(Serving::start(&c, &me, lock).await?);
                waiting_since = None;
                fleet.set_rpc_gateway(true);
                tracing::info!(instance = me, "fleet: serving `{p}/rpc` as the gateway");
            }
            Err(LockError::Held) => {
                let since = *waiting_since.get_or_insert_with(Instant::now);
                if since.elapsed() > LOCK_WARNING {
                    tracing::warn!(
                        instance = me,
                        "fleet: elected rpc gateway, but another process still holds \
                         fleet-gateway.lock (a stopped instance?); `{p}/rpc` is unserved"
                    );
                    waiting_since = Some(Instant::now());
                }
            }
            Err(e) => tracing::error!(instance = me, "fleet: the rpc gateway's lock: {e}"),
        }
    }
    if let Some(s) = serving.take() {
        s.stop().await;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn holders(ids: &[&str]) -> Holders {
        Holders(ids.iter().map(|s| s.to_string()).collect())
    }

    #[test]
    fn the_smallest_ready_instance_is_elected() {
        assert!(elected(&holders(&["a", "b", "c"]), "a"));
        assert!(!elected(&holders(&["a", "b", "c"]), "b"));
        assert!(elected(&holders(&["b", "c"]), "b"));
        assert!(!elected(&holders(&["a", "c"]), "c"));
    }
}
