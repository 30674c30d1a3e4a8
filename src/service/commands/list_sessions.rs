//! `list_sessions`: the sessions `caller` may see, sorted by name.

use crate::api::SessionList;
use crate::service::{Caller, Service};

impl Service {
    pub(super) fn list_sessions(&self, caller: &Caller) -> SessionList {
        SessionList {
            sessions: self
                .sessions()
                .iter()
                .filter(|s| caller.may_see(s))
                .map(|s| {
                    let mut info = s.info();
                    info.instance = self.owning_instance();
                    info
                })
                .collect(),
        }
    }
}
