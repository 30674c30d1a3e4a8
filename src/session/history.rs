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
}

fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// Pushes `item`, dropping the oldest beyond `cap`; counts what was dropped.
fn push_bounded<T>(queue: &mut VecDeque<T>, item: T, cap: usize, dropped: &mut u64) {
    queue.push_back(item);
    while queue.len() > cap {
        queue.pop_front();
        *dropped += 1;
    }
}

impl History {
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
                push_bounded(
                    &mut self.events,
                    logged(event),
                    LOGGED_EVENTS,
                    &mut self.dropped,
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
                push_bounded(
                    &mut self.events,
                    logged(event),
                    LOGGED_EVENTS,
                    &mut self.dropped,
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
                push_bounded(
                    &mut self.events,
                    logged(event),
                    LOGGED_EVENTS,
                    &mut self.dropped,
                );
                push_bounded(
                    &mut self.rejected,
                    logged(event),
                    REJECTIONS,
                    &mut self.dropped,
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
        // Not `stats()`: that also walks the session's memory, which this does not need.
        let last_error = self.last_error_locked(&self.lock());
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
