//! The web view's login sessions: what its cookie names (issue 52, item 8). The cookie used to
//! hold the token itself, hex-encoded: anyone who read it (a log, a shared browser profile)
//! held a credential that could write, for as long as the token lived. It now holds a random
//! id that means something only to this process: it reads as its token's label, expires after
//! [`LIFETIME`], is revoked by `POST /v1/logout`, and dies with the process.

use std::collections::HashMap;
use std::io::Read;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

/// How long a login lasts (also the cookie's `Max-Age`).
pub const LIFETIME: Duration = Duration::from_secs(12 * 3600);
/// Logins held at most: beyond, the expired ones are dropped, then the oldest.
const MAX_SESSIONS: usize = 10_000;
/// Random bytes in an id (hex in the cookie).
const ID_BYTES: usize = 32;

#[derive(Debug, thiserror::Error)]
#[error("no random bytes for a login id: {0}")]
pub struct NoRandomness(#[from] std::io::Error);

#[derive(Debug)]
struct Login {
    label: Arc<str>,
    expires: Instant,
}

#[derive(Debug, Default)]
pub struct WebSessions {
    by_id: Mutex<HashMap<String, Login>>,
}

impl WebSessions {
    /// A new login for `label`: the id its cookie carries.
    pub fn open(&self, label: Arc<str>) -> Result<String, NoRandomness> {
        let mut bytes = [0u8; ID_BYTES];
        std::fs::File::open("/dev/urandom")?.read_exact(&mut bytes)?;
        let id = hex::encode(bytes);
        let now = Instant::now();
        let mut by_id = self.by_id.lock().unwrap_or_else(PoisonError::into_inner);
        if by_id.len() >= MAX_SESSIONS {
            by_id.retain(|_, login| login.expires > now);
        }
        if by_id.len() >= MAX_SESSIONS {
            let oldest = by_id
                .iter()
                .min_by_key(|(_, login)| login.expires)
                .map(|(id, _)| id.clone());
            if let Some(oldest) = oldest {
                by_id.remove(&oldest);
            }
        }
        let login = Login {
            label,
            expires: now + LIFETIME,
        };
        by_id.insert(id.clone(), login);
        Ok(id)
    }

    /// The label the login `id` reads as, while it has not expired or been closed.
    pub fn label_of(&self, id: &str) -> Option<Arc<str>> {
        let mut by_id = self.by_id.lock().unwrap_or_else(PoisonError::into_inner);
        let login = by_id.get(id)?;
        if login.expires <= Instant::now() {
            by_id.remove(id);
            return None;
        }
        Some(Arc::clone(&login.label))
    }

    /// Ends the login `id` (logout): its cookie no longer reads anything.
    pub fn close(&self, id: &str) {
        let mut by_id = self.by_id.lock().unwrap_or_else(PoisonError::into_inner);
        by_id.remove(id);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_id_reads_as_its_label_until_closed() {
        let sessions = WebSessions::default();
        let id = sessions.open("alice".into()).unwrap();
        assert_eq!(id.len(), 2 * ID_BYTES);
        assert_eq!(sessions.label_of(&id).as_deref(), Some("alice"));
        assert_ne!(sessions.open("alice".into()).unwrap(), id);
        sessions.close(&id);
        assert_eq!(sessions.label_of(&id), None);
        assert_eq!(sessions.label_of("zz"), None);
    }
}
