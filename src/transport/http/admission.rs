//! Which accepted connections are served, and which give way to newer ones.
//!
//! - Under the cap (`http.max_connections`) every connection holds a slot until its socket
//!   closes.
//! - With tokens on, a connection on which no request has yet carried a valid credential is
//!   *unproven*, and holds its slot only until the cap is reached: then each newcomer takes the
//!   slot of an unproven connection, which closes (the oldest that sent a request without a
//!   credential, else the oldest that has sent nothing yet). Connections that have authenticated
//!   are never displaced, so clients without a token can neither keep authenticated clients out
//!   (issue 52, item 3: 4 096 stalled `POST /v1/login` bodies held every slot for 75 s) nor
//!   take slots from those already in; and an authenticated client only has to send its first
//!   request before all the unproven connections opened after it have displaced it.
//! - Beyond the cap, a reserve of [`RESERVE_CONNECTIONS`] answers probes only (see `listener`);
//!   when it is full a newcomer displaces the oldest reserve connection that has not sent a
//!   request yet.

use std::collections::VecDeque;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, PoisonError, Weak};
use std::time::Duration;

use tokio::sync::{oneshot, OwnedSemaphorePermit, Semaphore};

/// Connections beyond the cap that may still ask for health and metrics.
pub const RESERVE_CONNECTIONS: usize = 32;

/// A connection's slot under the cap; emptied when a newcomer takes it over.
pub(super) type SlotCell = Mutex<Option<OwnedSemaphorePermit>>;

/// What is known about a connection, shared by its task, the accept loop and the auth layer.
#[derive(Default)]
pub(super) struct Standing {
    has_request: AtomicBool,
    authenticated: AtomicBool,
}

impl Standing {
    pub(super) fn request_arrived(&self) {
        self.has_request.store(true, Ordering::Relaxed);
    }

    fn has_request(&self) -> bool {
        self.has_request.load(Ordering::Relaxed)
    }

    fn authenticated(&self) -> bool {
        self.authenticated.load(Ordering::Relaxed)
    }
}

/// Left in every request's extensions by the listener: the auth layer marks the connection as
/// authenticated through it and reads the limits an unauthenticated request is held to.
#[derive(Clone)]
pub struct ConnectionContext {
    pub(super) peer: SocketAddr,
    /// The connection's header timeout: also how long an unauthenticated body may take.
    pub(super) header_timeout: Duration,
    pub(super) standing: Arc<Standing>,
}

impl ConnectionContext {
    /// A request on this connection carried a valid credential: it is no longer displaced.
    pub(super) fn authenticated(&self) {
        self.standing.authenticated.store(true, Ordering::Relaxed);
    }
}

/// An admitted connection's side of its place.
pub(super) struct Ticket {
    /// Resolves with `Ok` when the connection must close for a newcomer.
    pub(super) evicted: oneshot::Receiver<()>,
    pub(super) standing: Arc<Standing>,
    /// Its slot under the cap; `None` for a reserve connection.
    pub(super) slot: Option<Arc<SlotCell>>,
}

/// The accept loop's side of a connection that may be displaced.
struct Place {
    evict: oneshot::Sender<()>,
    standing: Arc<Standing>,
    slot: Weak<SlotCell>,
}

impl Place {
    fn new(slot: Option<OwnedSemaphorePermit>) -> (Self, Ticket) {
        let (evict, evicted) = oneshot::channel();
        let standing = Arc::new(Standing::default());
        let slot = slot.map(|permit| Arc::new(Mutex::new(Some(permit))));
        let place = Self {
            evict,
            standing: Arc::clone(&standing),
            slot: slot.as_ref().map_or_else(Weak::new, Arc::downgrade),
        };
        let ticket = Ticket {
            evicted,
            standing,
            slot,
        };
        (place, ticket)
    }

    /// The connection has ended (its task dropped the receiver).
    fn closed(&self) -> bool {
        self.evict.is_closed()
    }

    /// Closes the connection, handing over its slot if it still has one.
    fn evict(self) -> Option<OwnedSemaphorePermit> {
        let permit = self
            .slot
            .upgrade()
            .and_then(|cell| cell.lock().unwrap_or_else(PoisonError::into_inner).take());
        let _ = self.evict.send(());
        permit
    }
}

pub(super) struct Admission {
    slots: Arc<Semaphore>,
    cap: usize,
    /// Unproven connections under the cap, oldest first (`None`: tokens off, nobody is
    /// displaced). Proven and closed ones are dropped from it at the cap, or when it has grown
    /// to twice the cap.
    unproven: Option<Mutex<VecDeque<Place>>>,
    /// Reserve connections, oldest first.
    reserve: Mutex<Vec<Place>>,
}

impl Admission {
    pub(super) fn new(cap: usize, displace_unauthenticated: bool) -> Self {
        Self {
            slots: Arc::new(Semaphore::new(cap)),
            cap,
            unproven: displace_unauthenticated.then(|| Mutex::new(VecDeque::new())),
            reserve: Mutex::new(Vec::new()),
        }
    }

    /// A place for a new connection: a slot under the cap, or in the reserve; `None`: close it.
    pub(super) fn admit(&self) -> Option<Ticket> {
        self.admit_under_cap().or_else(|| self.admit_to_reserve())
    }

    fn admit_under_cap(&self) -> Option<Ticket> {
        let permit = match Arc::clone(&self.slots).try_acquire_owned() {
            Ok(permit) => permit,
            Err(_) => self.displace_unproven()?,
        };
        let (place, ticket) = Place::new(Some(permit));
        if let Some(unproven) = &self.unproven {
            let mut unproven = unproven.lock().unwrap_or_else(PoisonError::into_inner);
            // Closed and proven places are otherwise only dropped when the cap is reached.
            if unproven.len() >= 2 * self.cap {
                unproven.retain(|p| !p.closed() && !p.standing.authenticated());
            }
            unproven.push_back(place);
        }
        Some(ticket)
    }

    /// The slot of an unproven connection, which closes: the oldest that has sent a request
    /// without a credential, or else the oldest that has sent nothing yet (a client that will
    /// authenticate is in the second kind only until its first request).
    fn displace_unproven(&self) -> Option<OwnedSemaphorePermit> {
        let mut unproven = self
            .unproven
            .as_ref()?
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        // Proven connections keep their slot: dropping their place leaves them open.
        unproven.retain(|p| !p.closed() && !p.standing.authenticated());
        loop {
            let victim = unproven
                .iter()
                .position(|p| p.standing.has_request())
                .or((!unproven.is_empty()).then_some(0))?;
            let place = unproven.remove(victim)?;
            // None: it closed just now, and its slot went back to the semaphore.
            if let Some(permit) = place.evict() {
                return Some(permit);
            }
            if let Ok(permit) = Arc::clone(&self.slots).try_acquire_owned() {
                return Some(permit);
            }
        }
    }

    /// A place in the reserve, evicting the oldest connection without a request when full.
    fn admit_to_reserve(&self) -> Option<Ticket> {
        let mut waiting = self.reserve.lock().unwrap_or_else(PoisonError::into_inner);
        waiting.retain(|place| !place.closed());
        if waiting.len() >= RESERVE_CONNECTIONS {
            let oldest_idle = waiting.iter().position(|p| !p.standing.has_request())?;
            waiting.remove(oldest_idle).evict();
        }
        let (place, ticket) = Place::new(None);
        waiting.push(place);
        Some(ticket)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unproven_connections_give_way_and_proven_ones_stay() {
        let admission = Admission::new(2, true);
        let mut first = admission.admit().unwrap();
        let second = admission.admit().unwrap();
        assert!(first.slot.is_some() && second.slot.is_some());
        // The cap is reached: the third takes the oldest unproven connection's slot.
        second.standing.authenticated.store(true, Ordering::Relaxed);
        let third = admission.admit().unwrap();
        assert!(third.slot.is_some());
        assert_eq!(first.evicted.try_recv(), Ok(()));
        assert!(first.slot.unwrap().lock().unwrap().is_none());
        // Then the third (the only unproven one) gives way; the proven second never does.
        let fourth = admission.admit().unwrap();
        assert!(fourth.slot.is_some());
        third.standing.authenticated.store(true, Ordering::Relaxed);
        fourth.standing.authenticated.store(true, Ordering::Relaxed);
        let fifth = admission.admit().unwrap();
        assert!(
            fifth.slot.is_none(),
            "all proven: the newcomer goes to the reserve"
        );
    }

    #[test]
    fn a_connection_that_sent_no_credential_goes_before_one_that_sent_nothing() {
        let admission = Admission::new(2, true);
        let mut quiet = admission.admit().unwrap();
        let mut anonymous = admission.admit().unwrap();
        anonymous.standing.request_arrived();
        let _newcomer = admission.admit().unwrap();
        assert_eq!(anonymous.evicted.try_recv(), Ok(()));
        assert!(quiet.evicted.try_recv().is_err());
    }

    #[test]
    fn without_tokens_nobody_is_displaced() {
        let admission = Admission::new(1, false);
        let mut first = admission.admit().unwrap();
        assert!(admission.admit().unwrap().slot.is_none());
        assert!(first.evicted.try_recv().is_err());
    }
}
