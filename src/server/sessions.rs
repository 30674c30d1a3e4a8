//! Sessions the config file asks for (`"sessions": [...]`, each a creation request): a robot's
//! ROS 2 binding, say, that should be there whenever the server runs, without a client to
//! create it. Each is created at start unless it exists already (recovered from the journal,
//! or created by another fleet instance), in which case it is left exactly as it is: the
//! journal, not the config, holds what a session was given.
//!
//! A request the service refuses as malformed (400, 422) stops the start, naming
//! `sessions[i].<field>`, as a bad config value would. A refusal that says nothing about the
//! request (the state directory holds an unloadable session of that name, the session cap) is
//! logged and the start goes on: the server is still of use for the rest.
//!
//! A name listed twice stops the start before anything is created: the second entry would
//! otherwise be taken for the first, which exists by then, and silently ignored.
//!
//! Each goes through the command API as a client's creation would (the config's server-wide
//! factor types included), unowned: any token reaches it, as with an anonymous zenoh client.

use crate::api::wire::CreateSession;
use crate::api::ErrorKind;
use crate::service::{Caller, Command, Recording, Reply, Service};

/// Creates the missing ones; `Err` with the message for a request that is wrong.
pub(super) async fn ensure(service: &Service, requests: &[CreateSession]) -> Result<(), String> {
    named_once(requests)?;
    for (i, request) in requests.iter().enumerate() {
        let Some(name) = request.session.as_deref() else {
            return Err(format!(
                "sessions[{i}].session: a configured session needs a name (it is created at \
                 every start unless it exists)"
            ));
        };
        match service
            .execute(
                &Caller::Trusted,
                Command::CreateSession(request.clone()),
                Recording::History,
            )
            .await
        {
            Ok(Reply::Created(info)) => {
                tracing::info!(session = name, "created from the config ({})", info.kind)
            }
            Ok(other) => unreachable!("a creation answers Created, not {other:?}"),
            Err(e) if e.body.code == "session_exists" => {
                tracing::debug!(session = name, "configured session exists: left as it is")
            }
            Err(e) if matches!(e.kind, ErrorKind::BadRequest | ErrorKind::Invalid) => {
                let field = e.body.field.map_or(String::new(), |f| format!(".{f}"));
                return Err(format!("sessions[{i}]{field}: {}", e.body.message));
            }
            Err(e) => tracing::warn!(
                session = name,
                "configured session not created: {} ({})",
                e.body.message,
                e.body.code
            ),
        }
    }
    Ok(())
}

/// Refuses a name given to two entries, naming the second.
fn named_once(requests: &[CreateSession]) -> Result<(), String> {
    let mut first = std::collections::HashMap::new();
    for (i, request) in requests.iter().enumerate() {
        if let Some(name) = request.session.as_deref() {
            if let Some(j) = first.insert(name, i) {
                return Err(format!(
                    "sessions[{i}].session: `{name}` is already the name of sessions[{j}]; \
                     a configured session is listed once"
                ));
            }
        }
    }
    Ok(())
}
