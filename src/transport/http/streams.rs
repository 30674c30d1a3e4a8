//! A session's events as Server-Sent Events and over a WebSocket (which also takes batches).

use std::convert::Infallible;
use std::sync::Arc;

use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::extract::{Path, State};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::Response;
use futures_util::Stream;
use tokio::sync::broadcast::error::RecvError;

use crate::service::Service;

use super::errors::HttpError;
use super::handlers::Caller;
use super::handlers::Shared;

#[utoipa::path(get, path = "/v1/sessions/{session}/events", tag = "reads",
    params(super::openapi::SessionPath),
    responses(
        (status = 200, description = "`text/event-stream`: each event's data is one \
            `SessionEvent` (schema below), its name the topic.", content_type = "text/event-stream",
            body = crate::api::wire::SessionEvent),
        (status = 401, response = super::openapi::Unauthorized),
        (status = 404, response = super::openapi::NotFound),
        (status = 421, response = super::openapi::Misdirected),
        (status = 429, response = super::openapi::TooMany),
        (status = 503, response = super::openapi::Unavailable)))]
/// Server-Sent Events: every session event, named by its topic (`acks`, `stats`, `poses`,
/// `summary`, `errors`); `lagged` when this client fell behind and missed some.
pub(super) async fn events(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, HttpError> {
    let receiver = service.subscribe_as(&caller.0, &session)?;
    let stream = futures_util::stream::unfold(receiver, |mut rx| async move {
        let event = match rx.recv().await {
            Ok(event) => Event::default()
                .event(event.topic())
                .json_data(&*event)
                .unwrap_or_else(|_| {
                    Event::default()
                        .event("errors")
                        .data("unserialisable event")
                }),
            Err(RecvError::Lagged(missed)) => Event::default()
                .event("lagged")
                .data(format!("{{\"missed\":{missed}}}")),
            Err(RecvError::Closed) => return None,
        };
        Some((Ok(event), rx))
    });
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()))
}

#[utoipa::path(get, path = "/v1/sessions/{session}/ws", tag = "reads",
    params(super::openapi::SessionPath),
    responses(
        (status = 101, description = "Switching to the WebSocket protocol: `SessionEvent`s out, \
            batches in."),
        (status = 400, response = super::openapi::BadRequest),
        (status = 401, response = super::openapi::Unauthorized),
        (status = 403, response = super::openapi::Forbidden),
        (status = 404, response = super::openapi::NotFound),
        (status = 421, response = super::openapi::Misdirected),
        (status = 429, response = super::openapi::TooMany),
        (status = 503, response = super::openapi::Unavailable)))]
/// WebSocket: the same events as the SSE stream (one JSON text message each, tagged by `type`;
/// `{"type": "lagged", "missed": n}` when this client fell behind), and text messages from the
/// client are batches for the session, acknowledged by the `ack` event or rejected by an `error`
/// event naming the problem.
pub(super) async fn websocket(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
    upgrade: WebSocketUpgrade,
) -> Result<Response, HttpError> {
    let events = service.subscribe_as(&caller.0, &session)?;
    let caller = caller.0;
    Ok(upgrade.on_upgrade(move |socket| serve_websocket(socket, service, caller, session, events)))
}

async fn serve_websocket(
    mut socket: WebSocket,
    service: Arc<Service>,
    caller: crate::service::Caller,
    session: String,
    mut events: tokio::sync::broadcast::Receiver<Arc<crate::api::wire::SessionEvent>>,
) {
    loop {
        tokio::select! {
            event = events.recv() => {
                let text = match event {
                    Ok(event) => serde_json::to_string(&*event).expect("events serialise"),
                    Err(RecvError::Lagged(missed)) => format!("{{\"type\":\"lagged\",\"missed\":{missed}}}"),
                    Err(RecvError::Closed) => break,
                };
                if socket.send(Message::Text(text.into())).await.is_err() {
                    break;
                }
            }
            incoming = socket.recv() => {
                let bytes = match incoming {
                    Some(Ok(Message::Text(text))) => text.as_bytes().to_vec(),
                    Some(Ok(Message::Binary(bytes))) => bytes.to_vec(),
                    Some(Ok(_)) => continue,
                    Some(Err(_)) | None => break,
                };
                // Accepted batches are acknowledged on the event stream; rejections too.
                if service.deliver(&caller, &session, "batch", &bytes).await.is_err() {
                    break; // the session is gone
                }
            }
        }
    }
}
