//! The command API's wire form: every operation both transports send ([`Command`]; zenoh:
//! this JSON on `factord/rpc`), each with its named request ([`requests`]) and reply
//! ([`replies`]) type, what it answers ([`Reply`]), and how an rpc payload or a topic message
//! is decoded into one ([`parse`]). What a command does is the service's: one file per command
//! under `service/commands/` (a layer above: not linked from here).

pub mod parse;
pub mod replies;
pub mod requests;

use serde::{Deserialize, Serialize};

use crate::api::wire::*;
pub use parse::{parse_command, parse_topic};
pub use replies::*;
pub use requests::*;

/// Every operation of the API, as both transports send it (zenoh: this JSON on `factord/rpc`):
/// `{"op": "<variant in snake_case>", ...its request's fields}`.
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(tag = "op", rename_all = "snake_case", deny_unknown_fields)]
pub enum Command {
    Health,
    ListSessions,
    CreateSession(CreateSession),
    DeleteSession(DeleteSession),
    ApplyBatch(ApplyBatch),
    Optimize(Optimize),
    SetAutoOptimize(SetAutoOptimize),
    DefineFactorTypes(DefineFactorTypes),
    GetEstimate(GetEstimate),
    ProducerStatus(ProducerQuery),
    ListProducers(ListProducers),
    ListRobots(ListRobots),
    ListOutliers(ListOutliers),
    GetStats(GetStats),
    Cancel(Cancel),
    Fusion(Fusion),
    GetGraph(GetGraph),
    GetHistory(GetHistory),
    GetMarginals(GetMarginals),
}

/// What a [`Command`] answers: its reply type, as the variant the service built.
#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
#[serde(untagged)]
pub enum Reply {
    Health(Health),
    Sessions(SessionList),
    Created(SessionInfo),
    Deleted(Deleted),
    Accepted(Accepted),
    Optimizing(Optimizing),
    AutoOptimize(AutoOptimizeSet),
    Estimate(Estimate),
    /// The estimate as a file (`estimate?format=tum|kitti|g2o|ply`): transports serve `body`
    /// as text where they can (HTTP, the zenoh estimate queryable), rpc as this JSON.
    Export(crate::api::export::Export),
    Stats(Box<SessionStats>),
    Cancelled(Cancelled),
    Fusion(crate::api::fusion::FusionAck),
    Graph(Box<crate::api::wire::Graph>),
    Producer(ProducerStatus),
    Producers(ProducerList),
    Robots(Box<crate::api::robots::RobotsReport>),
    Outliers(Box<crate::api::outliers::OutliersReport>),
    Marginals(Box<crate::api::wire::Marginals>),
    History(Box<crate::api::history::SessionHistory>),
}

impl Command {
    /// The session the command works on (none for `health`, `list_sessions`, and a creation).
    pub fn session(&self) -> Option<&str> {
        match self {
            Command::Health | Command::ListSessions | Command::CreateSession(_) => None,
            Command::DeleteSession(r) => Some(&r.session),
            Command::ApplyBatch(r) => Some(&r.session),
            Command::Optimize(r) => Some(&r.session),
            Command::SetAutoOptimize(r) => Some(&r.session),
            Command::DefineFactorTypes(r) => Some(&r.session),
            Command::GetEstimate(r) => Some(&r.session),
            Command::ProducerStatus(r) => Some(&r.session),
            Command::ListProducers(r) => Some(&r.session),
            Command::ListRobots(r) => Some(&r.session),
            Command::ListOutliers(r) => Some(&r.session),
            Command::GetStats(r) => Some(&r.session),
            Command::Cancel(r) => Some(&r.session),
            Command::Fusion(r) => Some(&r.session),
            Command::GetGraph(r) => Some(&r.session),
            Command::GetHistory(r) => Some(&r.session),
            Command::GetMarginals(r) => Some(&r.session),
        }
    }

    /// The estimate read a query string or selector asks for (HTTP, zenoh).
    pub fn get_estimate(session: String, query: EstimateQuery) -> Command {
        let EstimateQuery {
            since,
            from,
            to,
            after_producer,
            after_seq,
            after_timeout_ms,
            format,
            robot,
            frame,
        } = query;
        Command::GetEstimate(GetEstimate {
            session,
            since,
            from,
            to,
            after: AfterFields {
                after_producer,
                after_seq,
                after_timeout_ms,
            },
            format,
            robot,
            frame,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Command, crate::api::ServiceError> {
        parse_command(text.as_bytes(), 1000)
    }

    #[test]
    fn after_fields_are_flat_on_the_wire_and_read_as_whole_numbers() {
        let command = parse(
            r#"{"op": "optimize", "session": "s", "wait": true,
                "after_producer": "p", "after_seq": 3.0, "after_timeout_ms": 500}"#,
        )
        .unwrap();
        let Command::Optimize(optimize) = &command else {
            panic!("{command:?}")
        };
        assert_eq!(optimize.after.after_seq, Some(3));
        let after = optimize.after.clone().resolve().unwrap().unwrap();
        assert_eq!((after.producer.as_str(), after.seq), ("p", 3));
        assert_eq!(after.timeout, std::time::Duration::from_millis(500));
        // Written back as it came: flat.
        let written = serde_json::to_value(&command).unwrap();
        assert_eq!(written["after_producer"], "p");
        assert_eq!(written["op"], "optimize");
        let Command::GetEstimate(read) =
            parse(r#"{"op": "get_estimate", "session": "s", "after_seq": 2, "since": 1}"#).unwrap()
        else {
            panic!("a get_estimate")
        };
        assert_eq!((read.since, read.after.after_seq), (Some(1), Some(2)));
        assert_eq!(
            read.after.resolve().unwrap_err().body.field.as_deref(),
            Some("after_producer")
        );
    }

    #[test]
    fn an_unknown_field_is_refused_by_name_beside_flattened_ones_too() {
        for text in [
            r#"{"op": "optimize", "session": "s", "after_sequence": 3}"#,
            r#"{"op": "get_stats", "session": "s", "after_sequence": 3}"#,
            r#"{"op": "get_estimate", "session": "s", "after_sequence": 3}"#,
        ] {
            let error = parse(text).unwrap_err();
            assert_eq!(
                error.body.field.as_deref(),
                Some("after_sequence"),
                "{text}"
            );
        }
        let error = parse(r#"{"op": "optimize", "session": "s", "after_seq": 1.5}"#).unwrap_err();
        assert_eq!(error.kind, crate::api::ErrorKind::BadRequest);
    }

    #[test]
    fn every_command_names_its_session() {
        let command = parse(r#"{"op": "cancel", "session": "s"}"#).unwrap();
        assert_eq!(command.session(), Some("s"));
        assert_eq!(parse(r#"{"op": "health"}"#).unwrap().session(), None);
    }
}
