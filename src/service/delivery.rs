//! Messages sent to a session without a reply channel (a zenoh put, a WebSocket message).
//!
//! A delivery is decoded first ([`Service::decode_delivery`], which needs nothing of the
//! session's state and may run on any thread) and then delivered ([`Service::deliver_decoded`],
//! in the order the messages came). Transports that receive at full rate decode the next
//! message while the previous one is applied: decoding a 1000-factor batch costs about as much
//! as applying it. A decoded message runs as any command does ([`Service::execute`]), its
//! refusal recorded on the session's stream ([`Recording::Stream`]).

use super::{Caller, Recording, Service};
use crate::api::{Command, ServiceError};
use crate::session::Origin;

/// A message for a session's topic, decoded into its command, or refused.
pub struct Delivery {
    session: String,
    decoded: Result<Command, ServiceError>,
    /// The producer numbering of a batch that did not decode, read leniently: its producer
    /// waits for an ack or a refusal of exactly that number, so the refusal must carry it.
    undecoded_origin: Option<Origin>,
}

impl Delivery {
    /// A delivery refused before decoding (e.g. a payload beyond the size limit).
    pub fn refused(session: &str, error: ServiceError) -> Self {
        Self {
            session: session.into(),
            decoded: Err(error),
            undecoded_origin: None,
        }
    }

    /// A message a transport decoded itself (e.g. a ROS 2 message translated into a batch),
    /// or its refusal.
    pub fn decoded(session: &str, decoded: Result<Command, ServiceError>) -> Self {
        Self {
            session: session.into(),
            decoded,
            undecoded_origin: None,
        }
    }
}

/// `producer` and `producer_seq` of a batch payload that is JSON but not a valid batch (an
/// unknown field, a wrong type elsewhere); `None` when they are missing or invalid themselves.
fn lenient_origin(payload: &[u8]) -> Option<Origin> {
    #[derive(serde::Deserialize)]
    struct Numbering {
        producer: Option<String>,
        producer_seq: Option<serde_json::Value>,
    }
    let numbering: Numbering = serde_json::from_slice(payload).ok()?;
    let producer = numbering.producer?;
    crate::session::check_producer_id(&producer, "producer").ok()?;
    let seq = match numbering.producer_seq? {
        serde_json::Value::Number(n) => n.as_u64()?,
        serde_json::Value::String(s) => s.parse().ok()?,
        _ => return None,
    };
    (seq > 0).then_some(Origin { producer, seq })
}

impl Service {
    /// Decodes a message published on `session`'s topic `kind`
    /// (`api::command::parse_topic`); a session `caller` may not see is refused undecoded.
    pub fn decode_delivery(
        &self,
        caller: &Caller,
        session: &str,
        kind: &str,
        payload: &[u8],
    ) -> Delivery {
        let decoded = self.session_as(caller, session).and_then(|_| {
            crate::api::command::parse_topic(session, kind, payload, self.limits.max_batch_items)
        });
        let undecoded_origin = match (&decoded, kind) {
            (Err(_), "batch") => lenient_origin(payload),
            _ => None,
        };
        Delivery {
            session: session.into(),
            decoded,
            undecoded_origin,
        }
    }

    /// Executes a decoded message like any other command ([`Service::execute`], recorded on
    /// the stream). A rejection goes to the session's event stream, where its sender listens;
    /// it is returned only when there is no such session (and so no stream to put it on).
    pub async fn deliver_decoded(
        &self,
        caller: &Caller,
        delivery: Delivery,
    ) -> Result<(), ServiceError> {
        // Checked again: the session may have gone (or moved) while the message was decoded.
        let target = self.session_as(caller, &delivery.session)?;
        match delivery.decoded {
            Ok(command) => {
                // Refused or not, the outcome is on the stream already.
                let _ = self.execute(caller, command, Recording::Stream).await;
            }
            Err(error) => target.report_rejection(error, delivery.undecoded_origin),
        }
        Ok(())
    }

    /// [`Service::decode_delivery`] then [`Service::deliver_decoded`].
    pub async fn deliver(
        &self,
        caller: &Caller,
        session: &str,
        kind: &str,
        payload: &[u8],
    ) -> Result<(), ServiceError> {
        let delivery = self.decode_delivery(caller, session, kind, payload);
        self.deliver_decoded(caller, delivery).await
    }
}
