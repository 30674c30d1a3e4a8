//! One session's lock in a fleet: an OS lock (`flock`) on `sessions/<name>/lock`, taken without
//! waiting and held by the open file for as long as the session is loaded. The fleet's rpc
//! gateway holds one the same way, on `<state_dir>/fleet-gateway.lock` (`Fleet::gateway_lock`). The kernel releases
//! it however the process ends (a `kill -9` included), so a survivor can adopt the session at
//! once, and two instances can never both hold it: one journal, one writer.
//!
//! The file is never removed while a session lives (removing a lock file lets a second process
//! lock a new file while a first still holds the old one); it goes with its directory when the
//! session is deleted. After locking, the file at the path must still be the one locked: a
//! directory deleted and created again meanwhile has a new lock file, and that one is not held.

use std::fs::{File, OpenOptions};
use std::io;
use std::os::unix::fs::MetadataExt;
use std::path::Path;

/// A held lock (a session's, or the rpc gateway's); dropping it releases the lock.
#[derive(Debug)]
pub struct SessionLock {
    _file: File,
}

/// Why a lock was not taken.
#[derive(Debug, thiserror::Error)]
pub enum LockError {
    /// Another live process holds it (the owner, or one still releasing it).
    #[error("held by another instance")]
    Held,
    /// The session directory is gone (deleted meanwhile), or was replaced while locking.
    #[error("the session directory is gone")]
    Gone,
    #[error("{0}")]
    Io(#[from] io::Error),
}

impl SessionLock {
    /// Takes the lock of the session directory `dir`, without waiting.
    pub fn try_acquire(dir: &Path) -> Result<Self, LockError> {
        Self::try_acquire_file(&dir.join("lock"))
    }

    /// Takes the lock of the file at `path` (created if missing, in a directory that must
    /// exist), without waiting.
    pub fn try_acquire_file(path: &Path) -> Result<Self, LockError> {
        let file = match OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(path)
        {
            Ok(file) => file,
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Err(LockError::Gone),
            Err(e) => return Err(e.into()),
        };
        match file.try_lock() {
            Ok(()) => {}
            Err(std::fs::TryLockError::WouldBlock) => return Err(LockError::Held),
            Err(std::fs::TryLockError::Error(e)) => return Err(e.into()),
        }
        let held = file.metadata()?;
        match std::fs::metadata(path) {
            Ok(now) if now.ino() == held.ino() && now.dev() == held.dev() => {
                Ok(Self { _file: file })
            }
            Ok(_) => Err(LockError::Gone),
            Err(e) if e.kind() == io::ErrorKind::NotFound => Err(LockError::Gone),
            Err(e) => Err(e.into()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_held_lock_is_refused_until_released() {
        let dir = std::env::temp_dir().join(format!("factord-lock-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let first = SessionLock::try_acquire(&dir).unwrap();
        assert!(matches!(
            SessionLock::try_acquire(&dir),
            Err(LockError::Held)
        ));
        drop(first);
        let again = SessionLock::try_acquire(&dir).unwrap();
        drop(again);
        std::fs::remove_dir_all(&dir).unwrap();
        assert!(matches!(
            SessionLock::try_acquire(&dir),
            Err(LockError::Gone)
        ));
    }
}
