//! The exact solve of a session with a latency budget runs at a lower CPU priority.
//!
//! With a budget, the exact solve is off the request path by design: answers are provisional
//! until it lands. On a machine with as many busy threads as cores, it still competes with
//! what is on that path: the batch's handler, the journal's fdatasync leader and the
//! provisional solve. A thread that wakes up from an fdatasync then waits for a core, and that
//! wait can be as long as the scheduler's slice. A 300-byte append + fdatasync beside two busy
//! loops here had a p99 of 1.5–7.4 ms, and 0.20 ms when the loops ran 10 nicer. On the
//! 100 000-pose budgeted stream (snapshots in proportion to the journal in both), the answers
//! over 3 ms at 90 000–100 000 poses went from 602–666 to 437–581 with the exact solve 10
//! nicer.
//!
//! Only the solve's computation is niced. The landing takes the session's lock, which the
//! request path waits for, so the priority is restored before it: a niced thread preempted
//! while holding that lock would delay every answer (stop 65 niced whole workers and saw
//! that). Restoring the priority lowers a nice value, which Linux allows only with
//! `CAP_SYS_NICE` or a `RLIMIT_NICE` that permits it. Where it does not, nothing is niced,
//! since a pool worker left niced would slow the sessions without a budget, whose solves are
//! their answers.

/// How much nicer the exact solve runs.
const NICER_BY: i32 = 10;

/// While it lives, the calling thread runs [`NICER_BY`] nicer; dropping it restores the
/// thread's priority.
pub(super) struct Background {
    #[cfg(target_os = "linux")]
    previous: Option<i32>,
}

impl Background {
    /// Lowers the calling thread's priority, where it can be restored afterwards.
    pub fn enter() -> Self {
        #[cfg(target_os = "linux")]
        {
            let previous = restorable().then(thread_nice).flatten();
            if let Some(nice) = previous {
                if !set_thread_nice(nice + NICER_BY) {
                    return Self { previous: None };
                }
            }
            Self { previous }
        }
        #[cfg(not(target_os = "linux"))]
        Self {}
    }
}

impl Drop for Background {
    fn drop(&mut self) {
        #[cfg(target_os = "linux")]
        if let Some(nice) = self.previous {
            if !set_thread_nice(nice) {
                // `restorable` said it could; a thread left niced is only slower.
                tracing::warn!("could not restore a pool worker's priority after a solve");
            }
        }
    }
}

/// Lowers the calling thread's priority for the rest of its life: for a thread that only
/// computes in the background (`relinearize_beside`), so nothing needs restoring. It runs as
/// `SCHED_IDLE` (only on a core nothing else wants; any other thread that wakes up preempts it),
/// which any thread may ask for itself; where that fails, [`NICER_BY`] nicer.
pub(super) fn lower_for_good() {
    #[cfg(target_os = "linux")]
    {
        let param = libc::sched_param { sched_priority: 0 };
        // SAFETY: pid 0 is the calling thread; the parameter is a valid sched_param.
        if unsafe { libc::sched_setscheduler(0, libc::SCHED_IDLE, &param) } == 0 {
            return;
        }
        if let Some(nice) = thread_nice() {
            let _ = set_thread_nice(nice + NICER_BY);
        }
    }
}

/// Whether a thread may lower its nice value again after raising it (decided once, by a
/// probe thread, so that no pool worker is ever left niced).
#[cfg(target_os = "linux")]
fn restorable() -> bool {
    static RESTORABLE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *RESTORABLE.get_or_init(|| {
        std::thread::spawn(|| {
            let Some(nice) = thread_nice() else {
                return false;
            };
            set_thread_nice(nice + 1) && set_thread_nice(nice)
        })
        .join()
        .unwrap_or(false)
    })
}

/// The calling thread's nice value (on Linux, `PRIO_PROCESS` with a thread id is that thread).
#[cfg(target_os = "linux")]
fn thread_nice() -> Option<i32> {
    // SAFETY: gettid has no preconditions; getpriority reads the thread's priority. Its -1
    // is also a valid nice value, so errno is cleared first and checked after.
    unsafe {
        let tid = libc::gettid() as libc::id_t;
        *libc::__errno_location() = 0;
        let nice = libc::getpriority(libc::PRIO_PROCESS, tid);
        (*libc::__errno_location() == 0).then_some(nice)
    }
}

#[cfg(target_os = "linux")]
fn set_thread_nice(nice: i32) -> bool {
    // SAFETY: setpriority on the calling thread's own id changes only its priority.
    unsafe {
        let tid = libc::gettid() as libc::id_t;
        libc::setpriority(libc::PRIO_PROCESS, tid, nice.clamp(-20, 19)) == 0
    }
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    use super::*;

    #[test]
    fn the_priority_comes_back_after_the_solve() {
        std::thread::spawn(|| {
            let before = thread_nice().expect("readable");
            {
                let _background = Background::enter();
                let during = thread_nice().expect("readable");
                if restorable() {
                    assert_eq!(during, (before + NICER_BY).min(19));
                } else {
                    assert_eq!(during, before, "nothing niced where it cannot be undone");
                }
            }
            assert_eq!(thread_nice(), Some(before));
        })
        .join()
        .unwrap();
    }
}
