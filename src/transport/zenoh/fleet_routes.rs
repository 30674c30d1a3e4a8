//! Routing a fleet's commands over zenoh.
//!
//! - `<p>/rpc` (the one instance elected its gateway, `gateway.rs`) and `<p>/<s>/rpc` (the
//!   owner of `s`): a command without a session is answered here (`health`: this instance;
//!   `list_sessions`: every instance's, merged from their `info`); `create_session` without a
//!   name is named first (`Fleet::generate_name`); a command naming a session runs here when
//!   this instance owns it, and is otherwise forwarded to `<p>/@fleet/<owner>/rpc`, whose answer
//!   (or error) is relayed as is. A session moving between instances answers 503
//!   `session_moving` with Retry-After 1: the client retries.
//! - The owner declares `<p>/<s>/in/*`, `<p>/<s>/estimate`, `<p>/<s>/rpc` and the robots'
//!   queryables `<p>/<s>/robot/*/{estimate,map_from_odom}` when it loads session `s` and withdraws them when it releases or deletes it, so zenoh routes a robot's
//!   puts and queries to the owner alone.

use std::collections::hash_map::Entry;
use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;

use zenoh::query::Query;

use super::config::zenoh_error;
use super::fleet_proof;
use super::{answer_estimate, oversized, payload, Answer, Context};
use crate::service::fleet::{merge_session_lists, moving, Fleet, Route};
use crate::service::{Recording, ServiceError};

/// Whether a command for a session another instance owns is forwarded there (queries from
/// clients) or refused as moving (queries another instance forwarded: never twice).
#[derive(Clone, Copy, PartialEq, Eq)]
pub(super) enum Forward {
    Yes,
    No,
}

/// The fleet's answer to an rpc query: see the module's documentation.
pub(super) async fn route_rpc(c: &Context, query: &Query, forward: Forward) -> Answer {
    if let Some(refusal) = oversized(query.payload(), c.max_payload) {
        return Answer::of(Err(refusal));
    }
    let mut bytes = payload(query);
    // Undecodable: the command's own parser says why, here.
    let Ok(mut command) = serde_json::from_slice::<serde_json::Value>(&bytes) else {
        return super::rpc_answer(c, query).await;
    };
    let fleet = c.service.fleet().cloned();
    let Some(fleet) = fleet else {
        return super::rpc_answer(c, query).await;
    };
    match command.get("op").and_then(|op| op.as_str()) {
        Some("list_sessions") => return list_sessions(c).await,
        Some("create_session") if command.get("session").is_none_or(|s| s.is_null()) => {
            let f = Arc::clone(&fleet);
            match tokio::task::spawn_blocking(move || f.generate_name()).await {
                Ok(Ok(name)) => {
                    command["session"] = serde_json::Value::String(name);
                    bytes = serde_json::to_vec(&command).expect("JSON serialises");
                }
                Ok(Err(e)) => return Answer::of(Err(e)),
                Err(e) => return Answer::of(Err(ServiceError::internal(e.to_string()))),
            }
        }
        _ => {}
    }
    let Some(session) = command.get("session").and_then(|s| s.as_str()) else {
        return run_here(c, &bytes).await;
    };
    match c.service.route(session) {
        Route::Local => run_here(c, &bytes).await,
        Route::Moving => Answer::of(Err(moving(session))),
        Route::Remote { .. } if forward == Forward::No => Answer::of(Err(moving(session))),
        Route::Remote { instance, .. } => relay(c, &fleet, &instance, session, bytes).await,
    }
}

async fn run_here(c: &Context, bytes: &[u8]) -> Answer {
    let max_items = c.service.limits().max_batch_items;
    let result = match crate::service::parse_command(bytes, max_items) {
        Ok(command) => {
            c.service
                .execute(&c.caller, command, Recording::History)
                .await
        }
        Err(e) => Err(e),
    };
    Answer::of(result.map(|r| serde_json::to_vec(&r)))
}

/// Forwards the command to `instance` and returns its answer; none in time (or none that
/// proves it came from a member, see `fleet_proof`) is a move.
async fn relay(
    c: &Context,
    fleet: &Fleet,
    instance: &str,
    session: &str,
    bytes: Vec<u8>,
) -> Answer {
    // A command may wait for a solve (`wait`) or for a producer's batches (`after`).
    let timeout =
        Duration::from_millis(c.service.limits().wait_timeout_ms) + Duration::from_secs(65);
    let stamp = fleet_proof::stamp_rpc(fleet.key(), instance, &bytes);
    let get = c
        .zenoh
        .get(format!("{}/@fleet/{instance}/rpc", c.prefix))
        .payload(bytes)
        .attachment(stamp.as_ref().map(|s| s.encode()))
        .timeout(timeout)
        .await;
    let replies = match get {
        Ok(replies) => replies,
        Err(e) => {
            tracing::warn!(instance, "fleet: forwarding an rpc failed: {e}");
            return Answer::of(Err(moving(session)));
        }
    };
    while let Ok(reply) = replies.recv_async().await {
        match fleet_proof::open_answer(fleet.key(), stamp.as_ref(), &reply) {
            Some(answer) => return answer,
            None => tracing::warn!(
                instance,
                "fleet: an answer to a forwarded rpc without a valid fleet proof, ignored"
            ),
        }
    }
    Answer::of(Err(moving(session)))
}

/// Every instance's sessions, as zenoh peers may see them.
async fn list_sessions(c: &Context) -> Answer {
    let infos = super::fleet::infos(c, "*").await;
    let mut lists: Vec<_> = infos.into_iter().map(|i| i.sessions).collect();
    // This instance's own, even if its info query did not come back.
    if let Some(own) = c.service.fleet_info(&c.caller) {
        lists.push(own.sessions);
    }
    let body = serde_json::json!({ "sessions": merge_session_lists(lists) });
    Answer::of(Ok(serde_json::to_vec(&body)))
}

/// Keeps the keys of the sessions loaded here declared, and only those.
pub(super) fn start(c: &Context, fleet: Arc<Fleet>) -> tokio::task::JoinHandle<()> {
    let c = c.clone();
    tokio::spawn(async move {
        let mut loaded = fleet.loaded();
        let mut declared: HashMap<String, SessionKeys> = HashMap::new();
        loop {
            let now = loaded.borrow_and_update().clone();
            declared.retain(|name, _| now.contains(name));
            for name in now {
                if let Entry::Vacant(slot) = declared.entry(name) {
                    match SessionKeys::declare(&c, slot.key()).await {
                        Ok(keys) => {
                            slot.insert(keys);
                        }
                        Err(e) => {
                            let name = slot.key();
                            tracing::error!(session = name, "fleet: declaring its keys: {e}")
                        }
                    }
                }
            }
            if loaded.changed().await.is_err() {
                return;
            }
        }
    })
}

/// The tasks serving one session's keys; dropping it aborts them, which drops (undeclares)
/// their subscriber and queryables.
struct SessionKeys {
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

impl Drop for SessionKeys {
    fn drop(&mut self) {
        for t in &self.tasks {
            t.abort();
        }
    }
}

impl SessionKeys {
    async fn declare(c: &Context, name: &str) -> Result<Self, super::ZenohError> {
        let p = &c.prefix;
        let inputs = c
            .zenoh
            .declare_subscriber(format!("{p}/{name}/in/*"))
            .await
            .map_err(zenoh_error)?;
        let estimate = c
            .zenoh
            .declare_queryable(format!("{p}/{name}/estimate"))
            .complete(true)
            .await
            .map_err(zenoh_error)?;
        let rpc = c
            .zenoh
            .declare_queryable(format!("{p}/{name}/rpc"))
            .complete(true)
            .await
            .map_err(zenoh_error)?;
        let mut tasks = super::declare_robot_queries(c, &format!("{p}/{name}")).await?;
        // A session's puts are taken in the order they came.
        tasks.extend(super::inputs::take_inputs(c, inputs));
        let ctx = c.clone();
        tasks.push(tokio::spawn(async move {
            while let Ok(query) = estimate.recv_async().await {
                answer_estimate(&ctx, &query).await;
            }
        }));
        let ctx = c.clone();
        tasks.push(tokio::spawn(async move {
            while let Ok(query) = rpc.recv_async().await {
                let ctx = ctx.clone();
                tokio::spawn(async move {
                    route_rpc(&ctx, &query, Forward::Yes)
                        .await
                        .send(&query)
                        .await
                });
            }
        }));
        Ok(Self { tasks })
    }
}
