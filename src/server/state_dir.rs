//! The state directory: the lock that keeps a second server (or a server outside the fleet) off
//! it, and `server.json`, which tells scripts and tests where the running server listens.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::ServeError;

/// What a running server tells the world, written to `<state_dir>/server.json`.
#[derive(Debug, Serialize, Deserialize)]
pub struct ServerInfo {
    pub pid: u32,
    pub http: String,
    pub zenoh_listen: Vec<String>,
    pub zenoh_prefix: String,
    /// The fleet instance id (in a fleet).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub instance: Option<String>,
}

/// An exclusive hold on the state directory: an OS lock (`flock`) on `factord.lock`, held by the
/// open file for the process's life and released by the kernel however the process ends, so a
/// `kill -9` leaves no stale lock and two servers starting at once cannot both get it. The file
/// holds the holder's pid, for the message the next one prints; it is never removed (a removal
/// would let a third server lock a new file while a second still waits on the old one).
///
/// The instances of a fleet share the directory: each holds a *shared* lock on the file (and
/// each session's own lock, see `service::fleet`), so a server outside the fleet cannot start on
/// it, nor a fleet instance on a directory a lone server holds.
pub(super) struct StateDir {
    _lock: std::fs::File,
}

impl StateDir {
    /// Writes `server.json` (`server-<instance>.json` in a fleet, which shares the directory)
    /// and returns its path, which the server removes when it stops.
    pub(super) fn write_info(
        &self,
        config: &super::ServeConfig,
        http: &std::net::SocketAddr,
        instance: Option<&str>,
    ) -> Result<PathBuf, ServeError> {
        let info = ServerInfo {
            pid: std::process::id(),
            http: http.to_string(),
            zenoh_listen: match config.zenoh_enabled {
                true => config.zenoh.listen.clone(),
                false => Vec::new(),
            },
            zenoh_prefix: config.zenoh.prefix.clone(),
            instance: instance.map(str::to_string),
        };
        let path = config.state_dir.join(match instance {
            Some(id) => format!("server-{id}.json"),
            None => "server.json".into(),
        });
        std::fs::write(
            &path,
            serde_json::to_string_pretty(&info).expect("serialisable"),
        )
        .map_err(|e| ServeError::StateDir {
            dir: config.state_dir.clone(),
            message: e.to_string(),
        })?;
        Ok(path)
    }
}

impl StateDir {
    pub(super) fn open(dir: &Path, shared: bool) -> Result<Self, ServeError> {
        use std::io::{Seek, Write};
        let err = |message: String| ServeError::StateDir {
            dir: dir.into(),
            message,
        };
        std::fs::create_dir_all(dir).map_err(|e| err(e.to_string()))?;
        let path = dir.join("factord.lock");
        let mut lock = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(|e| err(format!("{}: {e}", path.display())))?;
        if shared {
            return match lock.try_lock_shared() {
                Ok(()) => Ok(Self { _lock: lock }),
                Err(std::fs::TryLockError::WouldBlock) => Err(err(format!(
                    "in use by {}, a factord outside the fleet (it holds the lock on {})",
                    lock_holder(&lock).map_or("another process".into(), |p| format!("process {p}")),
                    path.display()
                ))),
                Err(std::fs::TryLockError::Error(e)) => {
                    Err(err(format!("cannot lock {}: {e}", path.display())))
                }
            };
        }
        match lock.try_lock() {
            Ok(()) => {}
            Err(std::fs::TryLockError::WouldBlock) => {
                let holder = match lock_holder(&lock) {
                    Some(pid) => format!("process {pid}"),
                    None => "another process".to_string(),
                };
                return Err(err(format!(
                    "in use by {holder}, another factord serving it, or a fleet (it holds the \
                     lock on {})",
                    path.display()
                )));
            }
            Err(std::fs::TryLockError::Error(e)) => {
                return Err(err(format!("cannot lock {}: {e}", path.display())))
            }
        }
        let pid = std::process::id().to_string();
        lock.set_len(0)
            .and_then(|()| lock.rewind())
            .and_then(|()| lock.write_all(pid.as_bytes()))
            .map_err(|e| err(format!("{}: {e}", path.display())))?;
        Ok(Self { _lock: lock })
    }
}

/// The process holding the `flock` on `file`, as the kernel tells it in `/proc/locks`
/// (`1: FLOCK  ADVISORY  WRITE <pid> <major>:<minor>:<inode> 0 EOF`). The pid written into the
/// file cannot say it: the holder writes it only after taking the lock, so a second server
/// starting at that moment would read the previous holder's. `None` where there is no
/// `/proc/locks` or the holder is gone.
fn lock_holder(file: &std::fs::File) -> Option<u32> {
    use std::os::unix::fs::MetadataExt;
    let inode = file.metadata().ok()?.ino().to_string();
    let locks = std::fs::read_to_string("/proc/locks").ok()?;
    locks
        .lines()
        .filter(|line| line.contains("FLOCK") && !line.contains("->"))
        .find_map(|line| {
            let fields: Vec<&str> = line.split_whitespace().collect();
            let at = fields
                .iter()
                .position(|f| f.rsplit(':').next() == Some(inode.as_str()) && f.contains(':'))?;
            fields.get(at.checked_sub(1)?)?.parse().ok()
        })
}
