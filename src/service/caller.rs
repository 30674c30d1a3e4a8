//! Who sends a command, and so which sessions exist for it.
//!
//! Authorisation happens here, on the session *name the service resolves*, in the one place
//! every command passes through ([`super::Service::execute`]): never on the text of a URL or
//! a key expression, whose spellings (percent-encoding, trailing slashes, `%2573`) the adapters
//! decode differently. A session owned by another principal does not exist for the caller: it
//! gets exactly the 404 of a session that was never created, and the session is not listed.

use std::sync::Arc;

use crate::session::Session;

/// The principal behind a command.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Caller {
    /// Every session: in-process callers (the CLI, benchmarks, tests of the library), HTTP
    /// when no tokens are configured (loopback only), and zenoh when HTTP has no tokens either.
    Trusted,
    /// A principal, by label: an HTTP request whose bearer token has this label, or every
    /// zenoh peer when zenoh is authenticated and mapped to this label (`zenoh.principal`).
    /// Sees the sessions it created and the unowned ones; sessions it creates are its own.
    Principal(Arc<str>),
    /// Nobody in particular: a peer on an unauthenticated zenoh while HTTP requires tokens, or
    /// an HTTP request without a valid token on an open route (`/v1/health`, the pages).
    /// Sees unowned sessions only; sessions it creates are unowned.
    Anonymous,
}

impl Caller {
    /// Whether `session` exists for this caller.
    pub fn may_see(&self, session: &Session) -> bool {
        match (self, session.owner()) {
            (Caller::Trusted, _) | (_, None) => true,
            (Caller::Principal(label), Some(owner)) => label == owner,
            (Caller::Anonymous, Some(_)) => false,
        }
    }

    /// The owner of a session this caller creates.
    pub fn owner_of_new(&self) -> Option<Arc<str>> {
        match self {
            Caller::Principal(label) => Some(Arc::clone(label)),
            Caller::Trusted | Caller::Anonymous => None,
        }
    }

    /// Whether this caller sees every session (so that telling "does not exist" apart from
    /// "not yours" reveals nothing it could not list anyway).
    pub fn sees_everything(&self) -> bool {
        matches!(self, Caller::Trusted)
    }
}
