//! Messages sent to a session without a reply channel (a zenoh put, a WebSocket message).
//!
//! A delivery is decoded first ([`Service::decode_delivery`], which needs nothing of the
//! session's state and may run on any thread) and then delivered ([`Service::deliver_decoded`],
//! in the order the messages came). Transports that receive at full rate decode the next
//! message while the previous one is applied: decoding a 1000-factor batch costs about as much
//! as applying it.

use super::{Caller, Service};
use crate::api::{Command, ServiceError};
use crate::session::Origin;

/// A message for a session's topic, decoded into its command, or refused.
pub struct Delivery {
    session: String,
    decoded: Result<Command, ServiceError>,
}

impl Delivery {
    /// A delivery refused before decoding (e.g. a payload beyond the size limit).
    pub fn refused(session: &str, error: ServiceError) -> Self {
        Self {
            session: session.into(),
            decoded: Err(error),
        }
    }

    /// A message a transport decoded itself (e.g. a ROS 2 message translated into a batch),
    /// or its refusal.
    pub fn decoded(session: &str, decoded: Result<Command, ServiceError>) -> Self {
        Self {
            session: session.into(),
            decoded,
        }
    }
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
        Delivery {
            session: session.into(),
            decoded,
        }
    }

    /// Executes a decoded message like any other command. A rejection goes to the session's
    /// event stream, where its sender listens; it is returned only when there is no such
    /// session (and so no stream to put it on).
    pub async fn deliver_decoded(
        &self,
        caller: &Caller,
        delivery: Delivery,
    ) -> Result<(), ServiceError> {
        // Checked again: the session may have gone (or moved) while the message was decoded.
        let target = self.session_as(caller, &delivery.session)?;
        let mut origin = None;
        let outcome = match delivery.decoded {
            Ok(command) => {
                if let Command::ApplyBatch { batch, .. } = &command {
                    origin = Origin::of(batch).ok().flatten();
                }
                self.execute_as(caller, command).await.map(|_| ())
            }
            Err(e) => Err(e),
        };
        if let Err(error) = outcome {
            target.report_rejection(error, origin);
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
