//! Publishing a session's events on `<prefix>/<session>/out/<topic>`.

use std::sync::Arc;

use zenoh::qos::CongestionControl;

use crate::api::wire::SessionEvent;

/// Publishes a session's events until it is deleted (its event channel closes).
pub(super) fn forward(
    zenoh: zenoh::Session,
    prefix: String,
    session: &Arc<crate::session::Session>,
) {
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
