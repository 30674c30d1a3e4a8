//! A session's events as Server-Sent Events and over a WebSocket (which also takes batches).

use std::convert::Infallible;
use std::sync::Arc;

use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::extract::{Path, State};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::Response;
use futures_util::Stream;

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
/// `summary`, `errors`). A client that falls behind gets `lagged` (how many events it missed,
/// the session's sequences and every producer's `accepted_through`), then an `estimate` of
/// every variable changed meanwhile, instead of a silent gap.
pub(super) async fn events(
    State(service): Shared,
    caller: Caller,
    Path(session): Path<String>,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, HttpError> {
    let events = service.subscribe_as(&caller.0, &session)?;
    let stream = futures_util::stream::unfold(events, |mut events| async move {
        let event = events.next().await?;
        let sse = Event::default()
            .event(event.topic())
            .json_data(&*event)
            .unwrap_or_else(|_| {
                Event::default()
                    .event("errors")
                    .data("unserialisable event")
            });
        Some((Ok(sse), events))
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
/// the same `lagged` marker and re-synchronising estimate when this client fell behind), and
/// text messages from the client are batches for the session, acknowledged by the `ack` event
/// or rejected by an `error` event naming the problem.
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
    mut events: crate::session::EventStream,
) {
    loop {
        tokio::select! {
            event = events.next() => {
                let Some(event) = event else { break };
                let text = serde_json::to_string(&*event).expect("events serialise");
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
