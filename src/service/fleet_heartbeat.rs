//! Whether a fleet member has stopped (SIGSTOP, a frozen host), as the shared state directory
//! shows it: every instance rewrites `<state_dir>/fleet-heartbeats/<id>` with a new number every
//! `lease / 8`, and watches the others' files. A member whose number has not changed for a whole
//! lease, as this instance's own clock measures it, is stalled.
//!
//! Why a second signal beside zenoh's liveliness: a lost liveliness token says that the links
//! to a member broke, not that it stopped writing; a member cut off the network but running
//! still writes its sessions' journals. Only a member that is both gone from the membership and
//! stalled here has its sessions (and the rpc gateway) taken over without its lock; the
//! ownership epochs (`journal::epoch`) keep it from acknowledging anything should it resume.
//!
//! Staleness is measured from this instance's own observations, never by comparing clocks, and
//! the file is read again when asked: a member seen changing is not stalled, however long this
//! instance itself was stopped. A member that never wrote a heartbeat is never stalled.

use std::collections::HashMap;
use std::fs::{File, OpenOptions};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

pub struct Heartbeats {
    dir: PathBuf,
    me: String,
    lease: Duration,
    /// Every member's last number and when this instance first saw it.
    seen: Mutex<HashMap<String, (Vec<u8>, Instant)>>,
}

impl Heartbeats {
    /// Starts beating as `me` and watching the others, every `lease / 8`, on a thread of its
    /// own (not the async runtime: a busy runtime must not look like a stopped host), for as
    /// long as the returned value lives.
    pub fn start(state_dir: &Path, me: &str, lease: Duration) -> Arc<Self> {
        let heartbeats = Arc::new(Self {
            dir: state_dir.join("fleet-heartbeats"),
            me: me.to_string(),
            lease,
            seen: Mutex::new(HashMap::new()),
        });
        if let Err(e) = std::fs::create_dir_all(&heartbeats.dir) {
            tracing::warn!("fleet: cannot make {}: {e}", heartbeats.dir.display());
        }
        let weak = Arc::downgrade(&heartbeats);
        let period = (lease / 8).max(Duration::from_millis(10));
        let spawned = std::thread::Builder::new()
            .name("fleet-heartbeat".into())
            .spawn(move || {
                let mut file: Option<File> = None;
                // Never the number a previous process of this id stopped at.
                let mut beat = std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map_or(0, |d| d.as_nanos() as u64);
                loop {
                    let Some(heartbeats) = weak.upgrade() else {
                        return;
                    };
                    beat += 1;
                    heartbeats.beat(&mut file, beat);
                    heartbeats.watch();
                    drop(heartbeats);
                    std::thread::sleep(period);
                }
            });
        if let Err(e) = spawned {
            tracing::error!("fleet: cannot start the heartbeat thread: {e}");
        }
        heartbeats
    }

    fn path(&self, id: &str) -> PathBuf {
        self.dir.join(id)
    }

    /// Rewrites this instance's number in place (fixed width: a reader never sees a short file).
    fn beat(&self, file: &mut Option<File>, beat: u64) {
        if file.is_none() {
            *file = OpenOptions::new()
                .write(true)
                .create(true)
                .truncate(false)
                .open(self.path(&self.me))
                .map_err(|e| tracing::warn!("fleet: heartbeat file: {e}"))
                .ok();
        }
        if let Some(f) = file {
            if let Err(e) = f.write_all_at(format!("{beat:020}\n").as_bytes(), 0) {
                tracing::warn!("fleet: heartbeat: {e}");
                *file = None;
            }
        }
    }

    /// Reads every other member's number.
    fn watch(&self) {
        let Ok(entries) = std::fs::read_dir(&self.dir) else {
            return;
        };
        for entry in entries.flatten() {
            let id = entry.file_name().to_string_lossy().into_owned();
            if id != self.me {
                self.observe(&id);
            }
        }
    }

    /// Reads `id`'s number and records when it last changed; returns how long it has not.
    fn observe(&self, id: &str) -> Option<Duration> {
        let number = std::fs::read(self.path(id)).ok()?;
        let mut seen = self.seen.lock().unwrap_or_else(|p| p.into_inner());
        match seen.get(id) {
            Some((last, since)) if *last == number => Some(since.elapsed()),
            _ => {
                seen.insert(id.to_string(), (number, Instant::now()));
                Some(Duration::ZERO)
            }
        }
    }

    /// Whether member `id` has stopped beating for a whole lease (read now, see the module doc).
    pub fn stalled(&self, id: &str) -> bool {
        id != self.me && self.observe(id).is_some_and(|quiet| quiet >= self.lease)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_member_that_stops_beating_is_stalled_after_a_lease() {
        let dir = std::env::temp_dir().join(format!("factord-heartbeat-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let lease = Duration::from_millis(400);
        let a = Heartbeats::start(&dir, "a", lease);
        let b = Heartbeats::start(&dir, "b", lease);
        assert!(!a.stalled("never-beat"));
        std::thread::sleep(lease * 2);
        assert!(!a.stalled("b"), "b beats");
        assert!(!a.stalled("a"), "never itself");
        drop(b);
        std::thread::sleep(lease * 2);
        assert!(a.stalled("b"), "b stopped beating a lease ago");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
