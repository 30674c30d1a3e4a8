//! What a session remembers of its stream for the web view: every event it publishes passes
//! through [`History::record`], which keeps a bounded timeline of solves and the last events of
//! the log (see `api::history`). Nothing here is durable: a restarted server starts afresh.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use super::{Origin, Session};
use crate::api::history::{
    LoggedEvent, SessionHistory, TimelinePoint, LOGGED_EVENTS, REJECTIONS, TIMELINE_POINTS,
};
use crate::api::wire::SessionEvent;
use crate::api::ServiceError;

#[derive(Default)]
pub(super) struct History {
    timeline: VecDeque<TimelinePoint>,
    events: VecDeque<LoggedEvent>,
    rejected: VecDeque<LoggedEvent>,
    /// When each batch not yet reflected by a solve was accepted, by sequence (oldest first).
    accepted: VecDeque<(u64, Instant)>,
    dropped: u64,
    /// What `events` and `rejected` hold, kept as they change (see [`History::bytes`]).
    logged_bytes: usize,
}

fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// Pushes `item`, dropping the oldest beyond `cap`; counts what was dropped and returns it.
fn push_bounded<T>(queue: &mut VecDeque<T>, item: T, cap: usize, dropped: &mut u64) -> Option<T> {
    queue.push_back(item);
    if queue.len() <= cap {
        return None;
    }
    *dropped += 1;
    queue.pop_front()
}

/// [`push_bounded`] for the event log and the rejections, keeping their byte count.
fn push_logged(
    queue: &mut VecDeque<LoggedEvent>,
    item: LoggedEvent,
    cap: usize,
    dropped: &mut u64,
    bytes: &mut usize,
) {
    *bytes += logged_bytes(&item);
    if let Some(old) = push_bounded(queue, item, cap, dropped) {
        *bytes -= logged_bytes(&old);
    }
}

/// One logged event with its heap parts (an ack's ids, an error's text). An event the
/// stream's buffer still shares is counted here too, as the history outlives it.
fn logged_bytes(e: &LoggedEvent) -> usize {
    use std::mem::size_of;
    size_of::<LoggedEvent>()
        + size_of::<SessionEvent>()
        + match e.data.as_ref() {
            SessionEvent::Ack(ack) => {
                ack.factor_ids.len() * size_of::<crate::api::wire::FactorId>()
                    + ack.predicted.len() * size_of::<crate::variables::Key>()
                    + ack.session.len()
            }
            SessionEvent::Error { session, error, .. } => {
                session.len() + error.message.len() + error.field.as_ref().map_or(0, String::len)
            }
            _ => 0,
        }
}

impl History {
    /// What the history holds, for `memory_bytes`: O(1), from the logged events' byte count
    /// kept as they come and go and the fixed-size entries of the other queues.
    pub(super) fn bytes(&self) -> usize {
        use std::mem::size_of;
        self.timeline.len() * size_of::<TimelinePoint>()
            + self.accepted.len() * size_of::<(u64, Instant)>()
            + self.logged_bytes
    }

    pub(super) fn record(&mut self, event: &Arc<SessionEvent>) {
        let now = unix_ms();
        let logged = |event: &Arc<SessionEvent>| LoggedEvent {
            unix_ms: now,
            event: event.topic(),
            data: event.clone(),
        };
        match event.as_ref() {
            SessionEvent::Ack(ack) => {
                if !ack.reflected {
                    // Bounded like the timeline: a session that never solves keeps the newest.
                    let mut ignored = 0;
                    push_bounded(
                        &mut self.accepted,
                        (ack.sequence, Instant::now()),
                        TIMELINE_POINTS,
                        &mut ignored,
                    );
                }
                push_logged(
                    &mut self.events,
                    logged(event),
                    LOGGED_EVENTS,
                    &mut self.dropped,
                    &mut self.logged_bytes,
                );
            }
            SessionEvent::Summary {
                solve,
                sequence,
                summary,
                ..
            } => {
                let mut oldest = None;
                while let Some(&(seq, at)) = self.accepted.front() {
                    if seq > *sequence {
                        break;
                    }
                    oldest.get_or_insert(at);
                    self.accepted.pop_front();
                }
                let point = TimelinePoint {
                    unix_ms: now,
                    solve: *solve,
                    sequence: *sequence,
                    chi2: Some(summary.final_chi2).filter(|c| c.is_finite()),
                    solve_seconds: summary.solve_seconds,
                    latency_seconds: oldest.map(|at| at.elapsed().as_secs_f64()),
                    iterations: summary.iterations,
                    converged: summary.converged,
                };
                push_bounded(
                    &mut self.timeline,
                    point,
                    TIMELINE_POINTS,
                    &mut self.dropped,
                );
                push_logged(
                    &mut self.events,
                    logged(event),
                    LOGGED_EVENTS,
                    &mut self.dropped,
                    &mut self.logged_bytes,
                );
            }
            SessionEvent::State {
                iterations,
                update_seconds,
                ..
            } => {
                let point = TimelinePoint {
                    unix_ms: now,
                    solve: 0,
                    sequence: 0,
                    chi2: None,
                    solve_seconds: *update_seconds,
                    latency_seconds: Some(*update_seconds),
                    iterations: *iterations,
                    converged: true,
                };
                push_bounded(
                    &mut self.timeline,
                    point,
                    TIMELINE_POINTS,
                    &mut self.dropped,
                );
            }
            SessionEvent::Error { .. } => {
                push_logged(
                    &mut self.events,
                    logged(event),
                    LOGGED_EVENTS,
                    &mut self.dropped,
                    &mut self.logged_bytes,
                );
                push_logged(
                    &mut self.rejected,
                    logged(event),
                    REJECTIONS,
                    &mut self.dropped,
                    &mut self.logged_bytes,
                );
            }
            SessionEvent::Iteration { .. }
            | SessionEvent::Estimate(_)
            | SessionEvent::Window { .. }
            | SessionEvent::Lagged { .. } => {}
        }
    }
}

impl Session {
    /// Keeps a refusal answered to its sender (an rpc) in the history's rejected inputs, as
    /// streamed refusals are, without publishing it: `origin` names the batch's producer.
    pub fn note_rejection(&self, error: &ServiceError, origin: Option<Origin>) {
        let event = Arc::new(self.rejection_event(error.body.clone(), origin));
        let mut history = self.history.lock().unwrap_or_else(|p| p.into_inner());
        history.record(&event);
    }

    /// The session's timeline, recent events and rejections (see `api::history`).
    pub fn history(&self) -> SessionHistory {
        let last_error = self.last_error();
        let h = self.history.lock().unwrap_or_else(|p| p.into_inner());
        SessionHistory {
            session: self.name.clone(),
            timeline: h.timeline.iter().cloned().collect(),
            events: h.events.iter().cloned().collect(),
            rejected: h.rejected.iter().cloned().collect(),
            last_error,
            dropped: h.dropped,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::api::wire::BatchAck;

    fn ack(sequence: u64, factors: usize) -> Arc<SessionEvent> {
        Arc::new(SessionEvent::Ack(BatchAck {
            session: "s".into(),
            sequence,
            factor_ids: (0..factors as u64).collect(),
            predicted: Vec::new(),
            reflected: true,
            producer: None,
            producer_seq: None,
            accepted_through: None,
            duplicate: false,
        }))
    }

    #[test]
    fn its_bytes_count_what_logged_acks_carry_and_stay_bounded() {
        let mut history = History::default();
        history.record(&ack(1, 0));
        let small = history.bytes();
        history.record(&ack(2, 1000));
        assert!(history.bytes() >= small + 8000, "{}", history.bytes());
        for sequence in 3..10 * LOGGED_EVENTS as u64 {
            history.record(&ack(sequence, 1000));
        }
        // The log keeps the last LOGGED_EVENTS: its bytes stop growing.
        let full = history.bytes();
        assert!(
            full >= LOGGED_EVENTS * 8000 && full < LOGGED_EVENTS * 9000,
            "{full}"
        );
    }
}
