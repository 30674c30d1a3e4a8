//! Publishing a session's events on `<prefix>/<session>/out/<topic>`, and its estimates also in
//! binary on `<prefix>/<session>/bin/poses` (`crate::api::poses_binary`: about 40 bytes an SE(2)
//! pose against about 100 in JSON, and nothing to format or parse). The binary key is outside
//! `out/`, so subscribers of `out/**` keep receiving JSON only.
//!
//! The publisher reads through the session's [`crate::session::EventStream`], so it never loses
//! silently: after a lag it publishes the `lagged` marker on every topic key of the session (a
//! subscriber of any one topic learns it missed something and every producer's cumulative
//! progress), then the estimate of what changed meanwhile. The marker is JSON on every key, `bin/poses` included
//! (it starts with `{`, a binary estimate with `FDPB`; the zenoh encoding says which too).
//!
//! To keep up at full rate it drains what is queued and publishes estimates coalesced: the
//! estimate events of one drained run become one (the latest value of each variable), published
//! where the last of them was; everything else is published as it came, in order.
//! Acknowledgements, estimates, summaries, errors and markers are put with
//! `CongestionControl::Block` (a slow network slows the publisher, whose lag is then reported,
//! instead of zenoh dropping them) and express (sent at once, not held back to be batched with
//! later ones); iteration statistics may be dropped, and batched.
//!
//! An event is serialised and put only on the topics some subscriber would receive it on (in
//! this process, on a peer, or behind a router: zenoh's matching status of a publisher
//! declared per topic key, kept in a flag by a matching listener). A put that matches nobody
//! reaches nobody, so skipping it changes nothing a subscriber sees; it saves the
//! serialisation, which for the estimate after a loop closure (thousands of variables) costs
//! milliseconds of a core the solves share. A run nobody would receive any of is dropped
//! without handing it to a blocking thread: a session whose clients all use HTTP costs its
//! zenoh publisher a wake-up per run, not also a thread switch.

use std::collections::BTreeMap;
use std::sync::Arc;

use zenoh::bytes::Encoding;
use zenoh::pubsub::{PublicationBuilder, PublicationBuilderPut, PublisherBuilder};
use zenoh::qos::CongestionControl;
use zenoh::Wait;

use super::heard::Heard;
use super::robot_streams::RobotStreams;
use crate::api::poses_binary;
use crate::api::wire::{Estimate, SessionEvent};

/// The most events drained into one run: bounds the delay of the first of them.
const MAX_RUN: usize = 256;

/// Publishes a session's events until it is deleted (its event channel closes).
pub(super) fn forward(
    zenoh: zenoh::Session,
    prefix: String,
    session: &Arc<crate::session::Session>,
) {
    let mut events = session.stream();
    let topics = session.topics();
    let name = session.name.clone();
    let mut robots = RobotStreams::of(session, &prefix);
    let audience = robots.as_ref().map(RobotStreams::audience);
    tokio::spawn(async move {
        let listened = Arc::new(Listened::declare(&zenoh, &prefix, &name, topics).await);
        let mut run = Vec::with_capacity(MAX_RUN);
        loop {
            let first = match &audience {
                // A robot's key that gets an audience between estimates is served at once.
                Some(audience) => tokio::select! {
                    event = events.next() => event,
                    () = audience.notified() => {
                        let zenoh = zenoh.clone();
                        let served = on_blocking_thread(robots.take(), move |robots| {
                            if let Some(robots) = robots {
                                robots.serve_new_audiences(&zenoh);
                            }
                        });
                        robots = match served.await {
                            Some(back) => back,
                            None => return, // the runtime is shutting down
                        };
                        continue;
                    }
                },
                None => events.next().await,
            };
            let Some(first) = first else {
                return; // the session is gone
            };
            run.push(first);
            while run.len() < MAX_RUN {
                match events.try_next() {
                    Some(event) => run.push(event),
                    None => break,
                }
            }
            if let Some(robots) = robots.as_mut() {
                robots.discover(&zenoh, &run).await;
            }
            let robots_hear =
                |event: &SessionEvent| robots.as_ref().is_some_and(|r| r.hears(event));
            if !run
                .iter()
                .any(|event| listened.hears(event) || robots_hear(event))
            {
                run.clear();
                continue;
            }
            let (zenoh, name, listened) = (zenoh.clone(), name.clone(), Arc::clone(&listened));
            let events = std::mem::take(&mut run);
            let published = on_blocking_thread(robots.take(), move |robots| {
                let events = coalesce(events);
                publish(&zenoh, &name, &listened, &events);
                if let Some(robots) = robots {
                    robots.publish(&zenoh, &events);
                }
            });
            robots = match published.await {
                Some(back) => back,
                None => return, // the runtime is shutting down
            };
        }
    });
}

/// `work` on a blocking thread with the robot streams lent to it: a put is synchronous, and a
/// blocking one waits while the network is congested, so no runtime worker waits with it.
/// Gives the streams back; `None` when the runtime is shutting down.
async fn on_blocking_thread(
    mut lent: Option<RobotStreams>,
    work: impl FnOnce(Option<&mut RobotStreams>) + Send + 'static,
) -> Option<Option<RobotStreams>> {
    tokio::task::spawn_blocking(move || {
        work(lent.as_mut());
        lent
    })
    .await
    .ok()
}

/// A session's topic keys, each with a publisher declared on it so that zenoh keeps its
/// matching status up to date, and a listener that keeps that status in a flag.
struct Listened {
    topics: Vec<Topic>,
}

struct Topic {
    /// The events it carries: those whose [`SessionEvent::topic`] this is (and the markers).
    carries: &'static str,
    form: Form,
    key: String,
    heard: Heard,
}

/// How a topic's events are put.
#[derive(Clone, Copy, PartialEq, Debug)]
enum Form {
    Json,
    /// Estimates in `crate::api::poses_binary`'s layout; markers in JSON.
    PosesBinary,
}

impl Listened {
    async fn declare(
        zenoh: &zenoh::Session,
        prefix: &str,
        session: &str,
        topics: &[&'static str],
    ) -> Self {
        let mut declared = Vec::with_capacity(topics.len() + 1);
        for &carries in topics {
            declared.push((
                carries,
                Form::Json,
                format!("{prefix}/{session}/out/{carries}"),
            ));
            if carries == "poses" {
                declared.push((
                    carries,
                    Form::PosesBinary,
                    binary_poses_key(prefix, session),
                ));
            }
        }
        let mut listened = Vec::with_capacity(declared.len());
        for (carries, form, key) in declared {
            listened.push(Topic {
                carries,
                form,
                key: key.clone(),
                heard: Heard::declare(zenoh, key, None).await,
            });
        }
        Self { topics: listened }
    }

    /// The topics `event` goes on (a `lagged` marker: every topic) that some subscriber would
    /// receive a put on.
    fn hearing<'a>(&'a self, event: &'a SessionEvent) -> impl Iterator<Item = &'a Topic> + 'a {
        let lagged = matches!(event, SessionEvent::Lagged { .. });
        self.topics
            .iter()
            .filter(move |t| (lagged || t.carries == event.topic()) && t.heard.now())
    }

    /// Whether some subscriber would receive `event`.
    fn hears(&self, event: &SessionEvent) -> bool {
        self.hearing(event).next().is_some()
    }
}

/// The key of a session's estimates in binary.
fn binary_poses_key(prefix: &str, session: &str) -> String {
    format!("{prefix}/{session}/bin/poses")
}

/// Puts a drained run of events, estimates coalesced, `lagged` markers on every topic; an
/// event no subscriber would receive is not serialised.
fn publish(zenoh: &zenoh::Session, name: &str, listened: &Listened, run: &[Arc<SessionEvent>]) {
    for event in run {
        if let SessionEvent::Lagged { skipped, .. } = **event {
            tracing::warn!(
                "zenoh publisher of session {name} fell {skipped} events behind: published a \
                 lagged marker and the estimate's changes"
            );
        }
        let mut json = None;
        for topic in listened.hearing(event) {
            let (body, encoding) = match (topic.form, &**event) {
                (Form::PosesBinary, SessionEvent::Estimate(estimate)) => (
                    poses_binary::encode(estimate),
                    Encoding::APPLICATION_OCTET_STREAM,
                ),
                _ => (
                    json.get_or_insert_with(|| {
                        serde_json::to_vec(&**event).expect("events serialise")
                    })
                    .clone(),
                    Encoding::APPLICATION_JSON,
                ),
            };
            if let Err(e) = put_event(zenoh, &topic.key, body, encoding, event).wait() {
                tracing::warn!("zenoh publication for session {name} failed: {e}");
            }
        }
    }
}

/// The put of `event` (serialised in `body`, which `encoding` names) on `key`, with the event's
/// QoS: every put of an event goes through here, so none gets one setting without the other.
///
/// Everything a client waits on (acks, estimates, summaries, errors, markers) waits when zenoh's
/// queue is full, as an ack or an error may be the only word its sender gets, and is express:
/// sent at once, alone. While its link is busy, zenoh packs small messages into one batch and
/// holds the batch back as long as it keeps growing; right after a large estimate's fragments,
/// the summary that completes an update waited there (manhattanOlson3500 over zenoh with the
/// poses subscribed, 6 interleaved pairs: total median 4.59 → 3.94 s, p90 2.92 → 2.18 ms sent
/// at once; see benches/history/issue-16-incremental-engine.md). Iteration statistics may be
/// dropped (the next one supersedes them) and batched.
pub(super) fn put_event<'a>(
    zenoh: &'a zenoh::Session,
    key: &'a str,
    body: Vec<u8>,
    encoding: Encoding,
    event: &SessionEvent,
) -> PublicationBuilder<PublisherBuilder<'a, 'a>, PublicationBuilderPut> {
    let waited_on = !matches!(event, SessionEvent::Iteration { .. });
    let congestion = match waited_on {
        true => CongestionControl::Block,
        false => CongestionControl::Drop,
    };
    zenoh
        .put(key, body)
        .encoding(encoding)
        .congestion_control(congestion)
        .express(waited_on)
}

/// The put of `event` in JSON on `key`, for an event published outside a session's run (a
/// refused put that has no session to report it).
pub(super) fn put_json_event<'a>(
    zenoh: &'a zenoh::Session,
    key: &'a str,
    event: &SessionEvent,
) -> PublicationBuilder<PublisherBuilder<'a, 'a>, PublicationBuilderPut> {
    let body = serde_json::to_vec(event).expect("events serialise");
    put_event(zenoh, key, body, Encoding::APPLICATION_JSON, event)
}

/// `run` with its estimate events merged into one (the latest value of each variable, the
/// highest sequence) where the last of them was; the other events unchanged, in order.
fn coalesce(run: Vec<Arc<SessionEvent>>) -> Vec<Arc<SessionEvent>> {
    let estimates = run
        .iter()
        .filter(|e| matches!(***e, SessionEvent::Estimate(_)))
        .count();
    if estimates < 2 {
        return run;
    }
    let mut merged = BTreeMap::new();
    let (mut session, mut sequence) = (String::new(), 0);
    let mut seen = 0;
    let mut out = Vec::with_capacity(run.len() - estimates + 1);
    for event in run {
        let SessionEvent::Estimate(estimate) = &*event else {
            out.push(event);
            continue;
        };
        for v in &estimate.variables {
            merged.insert(v.key, v.clone());
        }
        session.clone_from(&estimate.session);
        sequence = sequence.max(estimate.sequence);
        seen += 1;
        if seen == estimates {
            out.push(Arc::new(SessionEvent::Estimate(Estimate {
                session: std::mem::take(&mut session),
                sequence,
                variables: std::mem::take(&mut merged).into_values().collect(),
            })));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::api::wire::{BatchAck, VariableValue};

    fn estimate(sequence: u64, values: &[(u64, f64)]) -> Arc<SessionEvent> {
        Arc::new(SessionEvent::Estimate(Estimate {
            session: "s".into(),
            sequence,
            variables: values
                .iter()
                .map(|&(key, x)| VariableValue {
                    key,
                    kind: "se2".into(),
                    value: smallvec::smallvec![x, 0.0, 0.0],
                    changed: sequence,
                    stamp: None,
                })
                .collect(),
        }))
    }

    fn ack(sequence: u64) -> Arc<SessionEvent> {
        Arc::new(SessionEvent::Ack(BatchAck {
            session: "s".into(),
            sequence,
            factor_ids: vec![],
            predicted: vec![],
            reflected: false,
            producer: None,
            producer_seq: None,
            accepted_through: None,
            duplicate: false,
        }))
    }

    #[test]
    fn estimates_merge_into_the_latest_value_of_each_variable_where_the_last_was() {
        let run = vec![
            ack(1),
            estimate(1, &[(1, 1.0)]),
            ack(2),
            estimate(2, &[(2, 2.0), (1, 1.5)]),
            ack(3),
            estimate(1, &[(0, 0.5)]),
            ack(4),
        ];
        let out = coalesce(run);
        let topics: Vec<&str> = out.iter().map(|e| e.topic()).collect();
        assert_eq!(topics, ["acks", "acks", "acks", "poses", "acks"]);
        let SessionEvent::Estimate(merged) = &*out[3] else {
            panic!("an estimate")
        };
        assert_eq!(merged.sequence, 2);
        let values: Vec<(u64, f64)> = merged
            .variables
            .iter()
            .map(|v| (v.key, v.value[0]))
            .collect();
        assert_eq!(values, [(0, 0.5), (1, 1.5), (2, 2.0)]);
    }

    #[test]
    fn a_run_with_one_estimate_is_unchanged() {
        let run = vec![ack(1), estimate(1, &[(1, 1.0)]), ack(2)];
        let out = coalesce(run.clone());
        assert!(out.iter().zip(&run).all(|(a, b)| Arc::ptr_eq(a, b)));
        assert_eq!(out.len(), 3);
    }
}
