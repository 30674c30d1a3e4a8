//! Puts on `<p>/<session>/in/<topic>`: decoded ahead, delivered in the order they came.
//!
//! A robot streaming 1000-factor batches keeps one decoding on a blocking thread while the
//! batch before it is applied, so ingest takes the larger of the two costs, not their sum.
//! Puts have no reply: rejections go to the session's stream (SSE and `out/errors`), or
//! straight to `out/errors` when there is no such session or the put is too large to read
//! (that refusal tells the sender nothing of the session).

use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use zenoh::handlers::FifoChannelHandler;
use zenoh::pubsub::Subscriber;
use zenoh::sample::Sample;

use super::{oversized, Context};
use crate::api::wire::SessionEvent;
use crate::service::Delivery;

/// Puts decoded ahead of the one being applied: enough to keep one decoding while one applies,
/// few enough that a slow session holds little decoded memory (each up to `max_body_bytes`).
const DECODE_AHEAD: usize = 2;

/// Payloads below this are decoded where they are received: a blocking thread's hand-off
/// (tens of microseconds) would cost more than the decoding of a pose or two.
const DECODE_INLINE_BYTES: usize = 16 * 1024;

enum Decoding {
    Ready(Box<Delivery>),
    Running(JoinHandle<Delivery>),
}

/// Starts the two tasks that take `inputs` (one subscriber's puts, in order): the first
/// decodes, the second delivers. Aborting both stops taking puts.
pub(super) fn take_inputs(
    c: &Context,
    inputs: Subscriber<FifoChannelHandler<Sample>>,
) -> [JoinHandle<()>; 2] {
    let (decoded_tx, mut decoded_rx) = mpsc::channel::<(String, Decoding)>(DECODE_AHEAD);
    let ctx = c.clone();
    let decode = tokio::spawn(async move {
        while let Ok(sample) = inputs.recv_async().await {
            let Some((name, decoding)) = decode(&ctx, sample) else {
                continue;
            };
            if decoded_tx.send((name, decoding)).await.is_err() {
                return;
            }
        }
    });
    let ctx = c.clone();
    let deliver = tokio::spawn(async move {
        while let Some((name, decoding)) = decoded_rx.recv().await {
            // At full rate this loop's receive is always ready: without this it never yields,
            // and the tasks its batches wake (the event publishers, in the worker's LIFO slot,
            // which no other worker steals) would wait until the stream pauses and then find
            // their events overwritten.
            tokio::task::consume_budget().await;
            let delivery = match decoding {
                Decoding::Ready(delivery) => *delivery,
                Decoding::Running(task) => match task.await {
                    Ok(delivery) => delivery,
                    Err(e) => {
                        let error = crate::api::ServiceError::internal(format!(
                            "decoding a put failed: {e}"
                        ));
                        Delivery::refused(&name, error)
                    }
                },
            };
            deliver(&ctx, &name, delivery).await;
        }
    });
    [decode, deliver]
}

/// The session a put is for and its decoding; `None` for a key that names no topic.
fn decode(c: &Context, sample: Sample) -> Option<(String, Decoding)> {
    let key = sample.key_expr().as_str();
    let mut parts = key.get(c.prefix.len() + 1..)?.split('/');
    let (Some(name), Some("in"), Some(what)) = (parts.next(), parts.next(), parts.next()) else {
        return None;
    };
    let (name, what) = (name.to_string(), what.to_string());
    if let Some(refusal) = oversized(Some(sample.payload()), c.max_payload) {
        return Some((
            name.clone(),
            Decoding::Ready(Box::new(Delivery::refused(&name, refusal))),
        ));
    }
    if sample.payload().len() < DECODE_INLINE_BYTES {
        let bytes = sample.payload().to_bytes();
        let delivery = c.service.decode_delivery(&c.caller, &name, &what, &bytes);
        return Some((name, Decoding::Ready(Box::new(delivery))));
    }
    let ctx = c.clone();
    let session = name.clone();
    let task = tokio::task::spawn_blocking(move || {
        let bytes = sample.payload().to_bytes();
        ctx.service
            .decode_delivery(&ctx.caller, &session, &what, &bytes)
    });
    Some((name, Decoding::Running(task)))
}

/// Delivers a decoded put; a refusal that has no session stream to go to goes to `out/errors`.
async fn deliver(c: &Context, name: &str, delivery: Delivery) {
    let Err(error) = c.service.deliver_decoded(&c.caller, delivery).await else {
        return;
    };
    let event = SessionEvent::Error {
        session: name.into(),
        sequence: None,
        error: error.body,
        producer: None,
        producer_seq: None,
    };
    // As the session's own events are published (zenoh's default would drop it at full rate).
    let key = format!("{}/{name}/out/errors", c.prefix);
    let _ = super::forward::put_json_event(&c.zenoh, &key, &event).await;
}
