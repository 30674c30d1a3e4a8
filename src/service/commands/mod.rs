//! The one entry every command goes through ([`Service::execute`]): the caller is explicit
//! (its sessions are resolved and authorised in [`Service::session_as`] and nowhere else), a
//! refused input is always recorded where its sender looks ([`Recording`]), and each command's
//! handling is its own file here, dispatched by one table.
//!
//! A new command: its request and reply types in `api::command`, a variant of `Command`, a
//! file here and its line in [`Service::dispatch`]; transports reach it as they are (zenoh's
//! rpc decodes any command), an HTTP route is one handler and one `routes!` line.

mod apply_batch;
mod cancel;
mod create_session;
mod define_factor_types;
mod delete_session;
mod fusion;
mod get_estimate;
mod get_graph;
mod get_history;
mod get_marginals;
mod get_stats;
mod health;
mod list_outliers;
mod list_producers;
mod list_robots;
mod list_sessions;
mod optimize;
mod producer_status;
mod set_auto_optimize;

use super::{Caller, Service};
use crate::api::wire::After;
use crate::api::{Command, Reply, ServiceError};
use crate::session::{Origin, Session};

/// Where the refusal of an input (a batch, fusion messages) is recorded besides its answer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Recording {
    /// A request with a reply (HTTP, zenoh `rpc`, in-process): the caller has its answer; a
    /// refused batch or fusion message is kept in the session's history too, where the web
    /// view lists rejected inputs.
    History,
    /// A message without a reply channel (a zenoh put, a WebSocket message): any refusal is an
    /// `error` event on the session's stream, where its sender listens (and so in its history).
    Stream,
}

impl Service {
    /// Runs `command` for `caller`, recording a refused input as `recording` says.
    pub async fn execute(
        &self,
        caller: &Caller,
        command: Command,
        recording: Recording,
    ) -> Result<Reply, ServiceError> {
        // Resolved before it runs, as the message's sender saw it (it may delete the session).
        let recorded = match (&command, recording) {
            (Command::ApplyBatch(r), _) => {
                Some((r.session.as_str(), Origin::of(&r.batch).ok().flatten()))
            }
            (Command::Fusion(r), _) => Some((r.session.as_str(), None)),
            (command, Recording::Stream) => command.session().map(|name| (name, None)),
            (_, Recording::History) => None,
        }
        .and_then(|(name, origin)| Some((self.session_as(caller, name).ok()?, origin)));
        let outcome = self.dispatch(caller, command).await;
        if let (Err(error), Some((session, origin))) = (&outcome, recorded) {
            match recording {
                Recording::History => session.note_rejection(error, origin),
                Recording::Stream => session.report_rejection(error.clone(), origin),
            }
        }
        outcome
    }

    /// One line per command: its file's handling, its reply.
    async fn dispatch(&self, caller: &Caller, command: Command) -> Result<Reply, ServiceError> {
        if !matches!(command, Command::Health) {
            self.refuse_when_stopping()?;
        }
        match command {
            Command::Health => Ok(Reply::Health(self.health(caller))),
            Command::ListSessions => Ok(Reply::Sessions(self.list_sessions(caller))),
            Command::CreateSession(r) => self.create_session(caller, r).await.map(Reply::Created),
            Command::DeleteSession(r) => self.delete_session(caller, r).map(Reply::Deleted),
            Command::ApplyBatch(r) => self.apply_batch(caller, r).await.map(Reply::Accepted),
            Command::Optimize(r) => self.optimize(caller, r).await.map(Reply::Optimizing),
            Command::SetAutoOptimize(r) => {
                self.set_auto_optimize(caller, r).map(Reply::AutoOptimize)
            }
            Command::DefineFactorTypes(r) => self
                .define_factor_types(caller, r)
                .await
                .map(Reply::Created),
            Command::GetEstimate(r) => self.get_estimate(caller, r).await,
            Command::ProducerStatus(r) => self.producer_status(caller, r).map(Reply::Producer),
            Command::ListProducers(r) => self.list_producers(caller, r).map(Reply::Producers),
            Command::ListRobots(r) => self
                .list_robots(caller, r)
                .map(|r| Reply::Robots(Box::new(r))),
            Command::ListOutliers(r) => self
                .list_outliers(caller, r)
                .map(|r| Reply::Outliers(Box::new(r))),
            Command::GetStats(r) => self.get_stats(caller, r).map(Reply::Stats),
            Command::Cancel(r) => self.cancel(caller, r).map(Reply::Cancelled),
            Command::Fusion(r) => self.fusion(caller, r).await.map(Reply::Fusion),
            Command::GetGraph(r) => self.get_graph(caller, r).map(Reply::Graph),
            Command::GetHistory(r) => self.get_history(caller, r).map(Reply::History),
            Command::GetMarginals(r) => self.get_marginals(caller, r).await.map(Reply::Marginals),
        }
    }
}

/// Waits for the batches a request says it comes after (`after_producer`, `after_seq`).
async fn wait_after(session: &Session, after: Option<After>) -> Result<(), ServiceError> {
    match after {
        Some(After {
            producer,
            seq,
            timeout,
        }) => {
            crate::session::check_producer_id(&producer, "after_producer")?;
            session.wait_after(&producer, seq, timeout).await
        }
        None => Ok(()),
    }
}
