//! Failed authentications per peer (issue 52, item 8: 3 000 wrong logins were answered at
//! 8 408/s). A wrong bearer token or a failed login spends one of a peer's [`BURST`] failures,
//! which refill at one per [`REFILL_EVERY`]; a peer whose budget is spent gets 429
//! `too_many_failures` (with `Retry-After`) for every bearer token and login, right or wrong,
//! until it has refilled by one: answering right guesses while refusing wrong ones would tell a
//! guesser when it had won. Requests without a credential (health, the pages) and login
//! cookies (random ids, not guessable) are not affected.
//!
//! A peer is its IPv4 address, or its IPv6 /64 (one host usually holds a whole /64). Behind a
//! reverse proxy every client is the proxy: its clients then share one budget.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::{Mutex, PoisonError};
use std::time::{Duration, Instant};

use crate::api::{ErrorKind, ServiceError};

/// Failures a peer may have in a row before it is throttled.
pub const BURST: u32 = 20;
/// One more failure is allowed after each of these.
pub const REFILL_EVERY: Duration = Duration::from_secs(3);
/// Peers remembered at most; beyond, peers whose budget is whole again are forgotten, and if
/// none is, the table is cleared (memory stays bounded whatever the number of addresses).
const MAX_PEERS: usize = 100_000;

/// A peer's spent budget: `spent` failures as of `at`.
#[derive(Clone, Copy)]
struct Spent {
    spent: f64,
    at: Instant,
}

impl Spent {
    /// Failures still counted at `now`, after refilling.
    fn now(&self, now: Instant) -> f64 {
        let refilled = now.duration_since(self.at).as_secs_f64() / REFILL_EVERY.as_secs_f64();
        (self.spent - refilled).max(0.0)
    }
}

#[derive(Default, Debug)]
pub struct FailureThrottle {
    peers: Mutex<HashMap<IpAddr, Spent>>,
}

impl std::fmt::Debug for Spent {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:.1}", self.spent)
    }
}

/// The key a peer's failures are counted under.
fn peer_key(ip: IpAddr) -> IpAddr {
    match ip {
        IpAddr::V4(_) => ip,
        IpAddr::V6(v6) => match v6.to_ipv4_mapped() {
            Some(v4) => IpAddr::V4(v4),
            None => {
                let prefix = u128::from(v6) & !((1u128 << 64) - 1);
                IpAddr::V6(prefix.into())
            }
        },
    }
}

impl FailureThrottle {
    /// 429 when `peer` has spent its budget of failures.
    pub fn check(&self, peer: IpAddr) -> Result<(), ServiceError> {
        let peers = self.peers.lock().unwrap_or_else(PoisonError::into_inner);
        let Some(spent) = peers.get(&peer_key(peer)) else {
            return Ok(());
        };
        let over = spent.now(Instant::now()) - (f64::from(BURST) - 1.0);
        if over <= 0.0 {
            return Ok(());
        }
        let wait = (over * REFILL_EVERY.as_secs_f64()).ceil().max(1.0) as u64;
        let mut error = ServiceError::new(
            ErrorKind::TooMany,
            "too_many_failures",
            format!(
                "too many failed authentications from this address; retry in {wait} s \
                 (at most {BURST} in a row, then one per {} s)",
                REFILL_EVERY.as_secs()
            ),
        )
        .at("authorization");
        error.body.retry_after = Some(wait);
        Err(error)
    }

    /// Counts a failed authentication from `peer`.
    pub fn failed(&self, peer: IpAddr) {
        crate::runtime::metrics::count_auth_failure();
        let now = Instant::now();
        let mut peers = self.peers.lock().unwrap_or_else(PoisonError::into_inner);
        if peers.len() >= MAX_PEERS {
            peers.retain(|_, s| s.now(now) > 0.0);
            if peers.len() >= MAX_PEERS {
                peers.clear();
            }
        }
        let entry = peers.entry(peer_key(peer)).or_insert(Spent {
            spent: 0.0,
            at: now,
        });
        *entry = Spent {
            spent: entry.now(now) + 1.0,
            at: now,
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_peer_is_throttled_after_its_burst_and_others_are_not() {
        let throttle = FailureThrottle::default();
        let peer: IpAddr = "192.0.2.7".parse().unwrap();
        for _ in 0..BURST - 1 {
            throttle.failed(peer);
            assert!(throttle.check(peer).is_ok());
        }
        throttle.failed(peer);
        let refused = throttle.check(peer).unwrap_err();
        assert_eq!(refused.body.code, "too_many_failures");
        assert_eq!(refused.body.status, 429);
        assert!(refused.body.retry_after.is_some_and(|s| s >= 1));
        assert!(throttle.check("192.0.2.8".parse().unwrap()).is_ok());
    }

    #[test]
    fn an_ipv6_host_is_its_64() {
        let a: IpAddr = "2001:db8::1".parse().unwrap();
        let b: IpAddr = "2001:db8::ffff:2".parse().unwrap();
        assert_eq!(peer_key(a), peer_key(b));
        let mapped: IpAddr = "::ffff:192.0.2.7".parse().unwrap();
        assert_eq!(peer_key(mapped), "192.0.2.7".parse::<IpAddr>().unwrap());
    }
}
