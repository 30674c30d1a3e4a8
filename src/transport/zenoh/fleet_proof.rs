//! How fleet members prove membership over zenoh (the scheme: `service::fleet_key`).
//!
//! - `info`: the asker puts a fresh nonce in the selector (`…/info?nonce=<hex>`); the member
//!   signs the nonce, the key the reply is sent on and the exact reply bytes, in the reply's
//!   attachment. An answer that does not verify is not a member's.
//! - A forwarded rpc (`<p>/@fleet/<owner>/rpc`) carries a stamp (time, nonce, proof over the
//!   owner's id and the payload) in its attachment; the owner accepts each stamp once, while
//!   fresh. Its answer is always a reply (zenoh's error replies carry no attachment): one byte
//!   saying reply or error, then the answer's bytes, signed over the stamp's nonce.
//!
//! On a trusted network (no key) nothing is signed or checked, and the answer is sent as it
//! would be to any caller.

use zenoh::query::{Query, Reply};
use zenoh::sample::Sample;

use super::Answer;
use crate::api::ErrorKind;
use crate::service::fleet::FleetInfo;
use crate::service::fleet_key::{FleetKey, Purpose, Stamp};
use crate::service::ServiceError;

/// The selector of instance `id`'s `info` (`*`: every instance's), with a fresh nonce when
/// members must prove themselves; returns the selector and the nonce.
pub(super) fn info_selector(
    prefix: &str,
    id: &str,
    key: Option<&FleetKey>,
) -> (String, Option<String>) {
    let key_expr = format!("{prefix}/@fleet/{id}/info");
    match key {
        Some(key) => {
            let nonce = key.nonce();
            (format!("{key_expr}?nonce={nonce}"), Some(nonce))
        }
        None => (key_expr, None),
    }
}

/// The attachment proving this instance's `info` reply `body`, sent on `reply_key`, to
/// `query` (`None` on a trusted network, or when the asker sent no nonce).
pub(super) fn sign_info(
    key: Option<&FleetKey>,
    query: &Query,
    reply_key: &str,
    body: &[u8],
) -> Option<String> {
    let nonce = query.parameters().get("nonce")?;
    Some(key?.sign(
        Purpose::Info,
        &[nonce.as_bytes(), reply_key.as_bytes(), body],
    ))
}

/// The `info` in `sample` when it proves itself a member's answer to `nonce` (anything that
/// parses, on a trusted network).
pub(super) fn verified_info(
    key: Option<&FleetKey>,
    nonce: Option<&str>,
    sample: &Sample,
) -> Option<FleetInfo> {
    let body = sample.payload().to_bytes();
    if let (Some(key), Some(nonce)) = (key, nonce) {
        let proof = sample.attachment()?.try_to_string().ok()?;
        let reply_key = sample.key_expr().as_str().as_bytes();
        let parts = [nonce.as_bytes(), reply_key, &body[..]];
        if key.verify(Purpose::Info, &parts, &proof).is_err() {
            tracing::warn!(
                key = sample.key_expr().as_str(),
                "fleet: an info answer without a valid fleet proof, ignored (not a member)"
            );
            return None;
        }
    }
    serde_json::from_slice(&body).ok()
}

/// The stamp of an rpc forwarded to instance `to` (`None` on a trusted network).
pub(super) fn stamp_rpc(key: Option<&FleetKey>, to: &str, payload: &[u8]) -> Option<Stamp> {
    Some(key?.stamp(Purpose::Rpc, &[to.as_bytes(), payload]))
}

/// Accepts a forwarded rpc addressed to this instance `me`: its stamp must verify, be fresh and
/// new. Returns the stamp (its nonce signs the answer); `None` on a trusted network.
pub(super) fn accept_rpc(
    key: Option<&FleetKey>,
    me: &str,
    query: &Query,
) -> Result<Option<Stamp>, ServiceError> {
    let Some(key) = key else {
        return Ok(None);
    };
    let refused = |why: String| {
        ServiceError::new(ErrorKind::Unauthorized, "fleet_proof_invalid", why).at("attachment")
    };
    let text = query
        .attachment()
        .and_then(|a| a.try_to_string().ok())
        .ok_or_else(|| refused("a forwarded command needs the forwarding member's proof".into()))?;
    let stamp = Stamp::decode(&text).map_err(|e| refused(e.to_string()))?;
    let payload = super::payload(query);
    key.accept_once(Purpose::Rpc, &[me.as_bytes(), &payload], &stamp)
        .map_err(|e| {
            tracing::warn!("fleet: a forwarded rpc refused: {e}");
            refused(e.to_string())
        })?;
    Ok(Some(stamp))
}

const REPLY: u8 = b'R';
const ERROR: u8 = b'E';

/// Sends `answer` to a forwarded rpc accepted with `stamp`: sealed and signed with a key, as
/// is without one.
pub(super) async fn send_sealed(
    key: Option<&FleetKey>,
    stamp: Option<&Stamp>,
    query: &Query,
    answer: Answer,
) {
    let (Some(key), Some(stamp)) = (key, stamp) else {
        return answer.send(query).await;
    };
    let (kind, body) = match answer {
        Answer::Reply(body) => (REPLY, body),
        Answer::Error(body) => (ERROR, body),
    };
    let mut sealed = Vec::with_capacity(body.len() + 1);
    sealed.push(kind);
    sealed.extend_from_slice(&body.to_bytes());
    let proof = key.sign(Purpose::RpcReply, &[stamp.nonce.as_bytes(), &sealed]);
    if let Err(e) = query
        .reply(query.key_expr().clone(), sealed)
        .attachment(proof)
        .await
    {
        tracing::warn!("zenoh reply failed: {e}");
    }
}

/// The answer in `reply` to an rpc forwarded with `stamp`, when it proves itself the
/// member's (any answer, on a trusted network).
pub(super) fn open_answer(
    key: Option<&FleetKey>,
    stamp: Option<&Stamp>,
    reply: &Reply,
) -> Option<Answer> {
    let (Some(key), Some(stamp)) = (key, stamp) else {
        return Some(match reply.result() {
            Ok(sample) => Answer::Reply(sample.payload().clone()),
            Err(error) => Answer::Error(error.payload().clone()),
        });
    };
    let sample = reply.result().ok()?;
    let sealed = sample.payload().to_bytes();
    let proof = sample.attachment()?.try_to_string().ok()?;
    key.verify(
        Purpose::RpcReply,
        &[stamp.nonce.as_bytes(), &sealed],
        &proof,
    )
    .ok()?;
    let (&kind, body) = sealed.split_first()?;
    match kind {
        REPLY => Some(Answer::Reply(body.to_vec().into())),
        ERROR => Some(Answer::Error(body.to_vec().into())),
        _ => None,
    }
}
