//! Ownership epochs: who may write a directory that several processes share (a fleet's session
//! directory, the fleet's rpc gateway), as files that are created once and never change.
//!
//! `epoch-<n>` (n ≥ 1) is the claim of epoch `n`, holding the id of the instance that made it.
//! A claim is written to a temporary file, fsynced, and hard-linked to its name: `link` fails
//! when the name exists, so of two instances claiming epoch `n` at once exactly one succeeds,
//! and a claim is never seen half written. The current epoch is the highest claim; claims are
//! made one above it, so `epoch-<n+1>` existing means epoch `n` is over for good (the *fence*:
//! a holder of epoch `n` checks it, with one `stat`, before each acknowledgement). A holder that
//! hands over cleanly adds `released-<n>`: its successor need not wait to see it stopped.
//!
//! An OS lock (`flock`) stays the fast path beside the epochs: a process that dies loses it at
//! once. A process that is stopped (SIGSTOP, a frozen host) keeps its lock but stops answering;
//! a successor then claims the next epoch without the lock, and the fence keeps the stopped
//! one, if it ever resumes, from acknowledging anything. Claims name their holder so that the
//! successor can ask whether that holder stopped (`service::fleet_heartbeat`).

use std::fs::File;
use std::io::{self, Write};
use std::path::{Path, PathBuf};

fn claim_path(dir: &Path, epoch: u64) -> PathBuf {
    dir.join(format!("epoch-{epoch}"))
}

fn released_path(dir: &Path, epoch: u64) -> PathBuf {
    dir.join(format!("released-{epoch}"))
}

/// The highest claim in `dir` and its holder; `None` when nothing was ever claimed there.
pub fn current(dir: &Path) -> io::Result<Option<(u64, String)>> {
    let mut highest: Option<u64> = None;
    for entry in std::fs::read_dir(dir)? {
        let name = entry?.file_name();
        let Some(n) = name
            .to_str()
            .and_then(|n| n.strip_prefix("epoch-"))
            .and_then(|n| n.parse::<u64>().ok())
        else {
            continue;
        };
        highest = Some(highest.map_or(n, |h| h.max(n)));
    }
    let Some(epoch) = highest else {
        return Ok(None);
    };
    let holder = std::fs::read_to_string(claim_path(dir, epoch))?;
    Ok(Some((epoch, holder.trim().to_string())))
}

/// Claims `epoch` in `dir` for `holder`: `Ok(false)` when another claim has it already.
pub fn claim(dir: &Path, epoch: u64, holder: &str) -> io::Result<bool> {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos());
    let tmp = dir.join(format!(".epoch-{epoch}-{holder}-{nanos}.tmp"));
    let written = (|| {
        let mut file = File::create(&tmp)?;
        file.write_all(holder.as_bytes())?;
        file.sync_all()
    })();
    let linked = written.and_then(|()| std::fs::hard_link(&tmp, claim_path(dir, epoch)));
    let _ = std::fs::remove_file(&tmp);
    match linked {
        Ok(()) => {
            File::open(dir)?.sync_all()?;
            Ok(true)
        }
        Err(e) if e.kind() == io::ErrorKind::AlreadyExists => Ok(false),
        Err(e) => Err(e),
    }
}

/// Whether epoch `epoch` of `dir` is over: a later one was claimed, or the directory (with its
/// claim) is gone. Epoch 0 (nothing claimed, a single instance) is never over.
pub fn superseded(dir: &Path, epoch: u64) -> bool {
    epoch > 0 && (claim_path(dir, epoch + 1).exists() || !claim_path(dir, epoch).exists())
}

/// Says that the holder of `epoch` handed it over cleanly (it writes nothing there any more).
pub fn release(dir: &Path, epoch: u64) -> io::Result<()> {
    File::create(released_path(dir, epoch)).map(drop)
}

/// Whether the holder of `epoch` handed it over cleanly.
pub fn released(dir: &Path, epoch: u64) -> bool {
    released_path(dir, epoch).exists()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_claim_per_epoch_and_a_later_one_fences_the_earlier() {
        let dir = std::env::temp_dir().join(format!("factord-epoch-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        assert_eq!(current(&dir).unwrap(), None);
        assert!(!superseded(&dir, 0), "epoch 0 is a single instance's");
        assert!(claim(&dir, 1, "a").unwrap());
        assert!(!claim(&dir, 1, "b").unwrap(), "epoch 1 is a's");
        assert_eq!(current(&dir).unwrap(), Some((1, "a".into())));
        assert!(!superseded(&dir, 1));
        assert!(!released(&dir, 1));
        release(&dir, 1).unwrap();
        assert!(released(&dir, 1));
        assert!(claim(&dir, 2, "b").unwrap());
        assert!(superseded(&dir, 1));
        assert!(!superseded(&dir, 2));
        assert_eq!(current(&dir).unwrap(), Some((2, "b".into())));
        // No temporary file is left beside the claims.
        let names: Vec<String> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert!(names.iter().all(|n| !n.ends_with(".tmp")), "{names:?}");
        std::fs::remove_dir_all(&dir).unwrap();
        assert!(superseded(&dir, 2), "a directory gone ends its epoch");
    }
}
