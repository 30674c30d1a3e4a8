//! The exact solve of a session with a latency budget runs at a lower CPU priority.
//!
//! With a budget, the exact solve is off the request path by design: answers are provisional
//! until it lands. On a machine with as many busy threads as cores, it still competes with
//! what is on that path: the batch's handler, the journal's fdatasync leader, the provisional
//! solve and the transports' threads. A thread that wakes up from an fdatasync then waits for a
//! core, and that wait can be as long as the scheduler's slice. A 300-byte append + fdatasync
//! beside two busy loops here had a p99 of 1.5–7.4 ms, and 0.20 ms when the loops ran 10
//! nicer. On the 100 000-pose budgeted stream, the answers over 3 ms at 90 000–100 000 poses
//! went from 602–666 to 437–581 with the exact solve 10 nicer (stop 65).
//!
//! It now computes as `SCHED_IDLE`: Linux's scheduler (EEVDF, 6.6 on) lets a waking thread
//! preempt an idle-policy thread at once, where a niced one may first finish its slice. Over
//! zenoh (where more threads are on the request path: the transport's own) the fdatasync waits
//! over 2 ms at 90 000–100 000 poses fell from 130–273 to 27–83 and the answers over 4 ms from
//! 323–412 to 233–235 (stop 79, `benches/history/issue-55-latency.md`). An idle-policy thread
//! gets almost nothing of a core something else wants (a weight of 3 against a nice-0
//! thread's 1 024, where nice 10 has 110), so a solve that has not landed within
//! [`STARVED_AFTER`] (a server busy with other sessions' solves) computes 10 nicer instead for
//! the rest of its turn: the exact estimate of a budgeted session is late there, never stalled.
//!
//! Only the solve's computation runs in the background. The landing takes the session's lock,
//! which the request path waits for, so the priority is restored before it: a thread
//! preempted while holding that lock would delay every answer (stop 65 niced whole workers and
//! saw that). So is each iteration's publication ([`foreground`]): it waits for the journal
//! (and may run the fdatasync the batches wait for) and takes the event history's lock. Leaving `SCHED_IDLE`, like lowering a nice value, is allowed only with
//! `CAP_SYS_NICE` or a `RLIMIT_NICE` that permits it. Where it is not, the solve computes at
//! the worker's priority, since a pool worker left in the background would slow the sessions
//! without a budget, whose solves are their answers.

#[cfg(target_os = "linux")]
use std::cell::RefCell;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// How much nicer a solve runs once it has starved for [`STARVED_AFTER`], or where
/// `SCHED_IDLE` cannot be set.
const NICER_BY: i32 = 10;
/// How long a solve computes as `SCHED_IDLE` before it computes [`NICER_BY`] nicer: longer
/// than the exact solves of the budgeted 100 000-pose stream take (7 of 28 700 over a second,
/// none over 2.5 s), so only a solve that other work keeps from a core gets there.
const STARVED_AFTER: Duration = Duration::from_secs(3);

/// While it lives, the calling thread computes in the background (see the module doc);
/// dropping it restores the thread's policy and priority.
pub(super) struct Background {
    #[cfg(target_os = "linux")]
    entered: Option<Entered>,
}

/// A thread in the background: shared with the timer that moves it to [`NICER_BY`] nicer.
#[cfg(target_os = "linux")]
struct Entered {
    thread: Arc<Mutex<Watched>>,
    timer: Option<tokio::task::JoinHandle<()>>,
}

#[cfg(target_os = "linux")]
struct Watched {
    tid: libc::pid_t,
    /// The thread's nice value before it entered the background.
    nice: i32,
    /// Computing in the background now: not left, nor in [`foreground`] (the timer renices
    /// only such a thread).
    active: bool,
    /// As `SCHED_IDLE` (else [`NICER_BY`] nicer, where the policy could not be set).
    idle: bool,
    /// [`STARVED_AFTER`] has passed: from then on it computes [`NICER_BY`] nicer.
    starved: bool,
}

#[cfg(target_os = "linux")]
impl Watched {
    /// Moves the thread (back) into the background: idle, or nicer once starved.
    fn background(&mut self) -> bool {
        self.active = true;
        match self.idle && !self.starved {
            true => set_policy(self.tid, libc::SCHED_IDLE),
            false => {
                set_policy(self.tid, libc::SCHED_OTHER) && set_nice(self.tid, self.nice + NICER_BY)
            }
        }
    }

    /// Gives the thread its own policy and priority back.
    fn foreground(&mut self) -> bool {
        self.active = false;
        set_policy(self.tid, libc::SCHED_OTHER) && set_nice(self.tid, self.nice)
    }
}

#[cfg(target_os = "linux")]
thread_local! {
    /// The background the calling thread computes in, if any (see [`foreground`]).
    static CURRENT: RefCell<Option<Arc<Mutex<Watched>>>> = const { RefCell::new(None) };
}

#[cfg(target_os = "linux")]
fn lock(thread: &Mutex<Watched>) -> std::sync::MutexGuard<'_, Watched> {
    thread.lock().unwrap_or_else(|p| p.into_inner())
}

/// Runs `work` at the calling thread's own priority when it computes in the background (a
/// solve's step that takes locks the request path takes too), then moves it back.
pub(super) fn foreground<T>(work: impl FnOnce() -> T) -> T {
    #[cfg(target_os = "linux")]
    if let Some(thread) = CURRENT.with(|c| c.borrow().clone()) {
        if !lock(&thread).foreground() {
            tracing::warn!("could not restore a pool worker's priority for a solve's step");
        }
        let result = work();
        // A thread left at its priority is only faster.
        let _ = lock(&thread).background();
        return result;
    }
    work()
}

impl Background {
    /// Moves the calling thread to the background where it can be restored afterwards; after
    /// [`STARVED_AFTER`], `runtime` moves it to [`NICER_BY`] nicer.
    pub fn enter(runtime: &tokio::runtime::Handle) -> Self {
        #[cfg(target_os = "linux")]
        {
            Self {
                entered: Entered::enter(runtime, STARVED_AFTER),
            }
        }
        #[cfg(not(target_os = "linux"))]
        {
            let _ = runtime;
            Self {}
        }
    }
}

#[cfg(target_os = "linux")]
impl Entered {
    fn enter(runtime: &tokio::runtime::Handle, starved_after: Duration) -> Option<Self> {
        let nice = restorable().then(thread_nice).flatten()?;
        let mut watched = Watched {
            tid: own_tid(),
            nice,
            active: false,
            idle: true,
            starved: false,
        };
        if !watched.background() {
            watched.idle = false;
            if !watched.background() {
                return None;
            }
        }
        let idle = watched.idle;
        let thread = Arc::new(Mutex::new(watched));
        CURRENT.with(|c| *c.borrow_mut() = Some(Arc::clone(&thread)));
        let timer = idle.then(|| {
            let thread = Arc::clone(&thread);
            runtime.spawn(async move {
                tokio::time::sleep(starved_after).await;
                // Under the lock: the thread neither leaves the background nor steps into the
                // foreground meanwhile; one in the foreground goes back nicer.
                let mut watched = lock(&thread);
                watched.starved = true;
                if watched.active && !watched.background() {
                    tracing::warn!("could not move a starved background solve to a nice value");
                }
            })
        });
        Some(Self { thread, timer })
    }
}

impl Drop for Background {
    fn drop(&mut self) {
        #[cfg(target_os = "linux")]
        if let Some(entered) = self.entered.take() {
            if let Some(timer) = entered.timer {
                timer.abort();
            }
            CURRENT.with(|c| *c.borrow_mut() = None);
            if !lock(&entered.thread).foreground() {
                // `restorable` said it could; a thread left in the background is only slower.
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
        let tid = own_tid();
        if !set_policy(tid, libc::SCHED_IDLE) {
            if let Some(nice) = thread_nice() {
                let _ = set_nice(tid, nice + NICER_BY);
            }
        }
    }
}

/// Whether a thread may lower its nice value again after raising it, and so leave
/// `SCHED_IDLE` (both need the same permission), decided once by a probe thread, so that no
/// pool worker is ever left in the background.
#[cfg(target_os = "linux")]
fn restorable() -> bool {
    static RESTORABLE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *RESTORABLE.get_or_init(|| {
        std::thread::spawn(|| {
            let Some(nice) = thread_nice() else {
                return false;
            };
            set_nice(own_tid(), nice + 1) && set_nice(own_tid(), nice)
        })
        .join()
        .unwrap_or(false)
    })
}

/// The calling thread's id (what `PRIO_PROCESS` and `sched_setscheduler` take for a thread).
#[cfg(target_os = "linux")]
fn own_tid() -> libc::pid_t {
    // SAFETY: gettid has no preconditions.
    unsafe { libc::gettid() }
}

/// The calling thread's nice value.
#[cfg(target_os = "linux")]
fn thread_nice() -> Option<i32> {
    // SAFETY: getpriority reads a thread's priority. Its -1 is also a valid nice value, so
    // errno is cleared first and checked after.
    unsafe {
        *libc::__errno_location() = 0;
        let nice = libc::getpriority(libc::PRIO_PROCESS, own_tid() as libc::id_t);
        (*libc::__errno_location() == 0).then_some(nice)
    }
}

/// Sets the nice value of thread `tid` of this process.
#[cfg(target_os = "linux")]
fn set_nice(tid: libc::pid_t, nice: i32) -> bool {
    // SAFETY: setpriority on a thread id of this process changes only that thread's priority.
    unsafe { libc::setpriority(libc::PRIO_PROCESS, tid as libc::id_t, nice.clamp(-20, 19)) == 0 }
}

/// Sets the scheduling policy of thread `tid` of this process (`SCHED_OTHER` or
/// `SCHED_IDLE`, whose static priority is 0; the nice value is kept).
#[cfg(target_os = "linux")]
fn set_policy(tid: libc::pid_t, policy: libc::c_int) -> bool {
    let param = libc::sched_param { sched_priority: 0 };
    // SAFETY: a thread id of this process and a valid sched_param.
    unsafe { libc::sched_setscheduler(tid, policy, &param) == 0 }
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    use super::*;

    fn policy() -> libc::c_int {
        // SAFETY: pid 0 is the calling thread.
        unsafe { libc::sched_getscheduler(0) }
    }

    /// Runs `check` on a thread of its own (whose priority it may change), with its nice value
    /// before and a runtime for the starvation timer.
    fn on_a_thread(check: impl FnOnce(i32, &tokio::runtime::Handle) + Send + 'static) {
        let runtime = tokio::runtime::Runtime::new().expect("a runtime");
        let handle = runtime.handle().clone();
        std::thread::spawn(move || check(thread_nice().expect("readable"), &handle))
            .join()
            .unwrap();
    }

    /// The solve computes as `SCHED_IDLE` (where it can come back), and its thread's policy and
    /// priority are back after it.
    #[test]
    fn the_priority_comes_back_after_the_solve() {
        on_a_thread(|before, handle| {
            {
                let _background = Background::enter(handle);
                if restorable() {
                    assert_eq!(policy(), libc::SCHED_IDLE);
                } else {
                    assert_eq!(
                        policy(),
                        libc::SCHED_OTHER,
                        "nothing moved where it cannot be undone"
                    );
                }
                assert_eq!(thread_nice(), Some(before));
            }
            assert_eq!(policy(), libc::SCHED_OTHER);
            assert_eq!(thread_nice(), Some(before));
        });
    }

    /// A step in the foreground runs at the thread's own priority, and the thread goes back to
    /// the background after it.
    #[test]
    fn a_step_in_the_foreground_runs_at_the_threads_own_priority() {
        on_a_thread(|before, handle| {
            assert_eq!(foreground(policy), libc::SCHED_OTHER, "outside: just runs");
            let background = Background::enter(handle);
            let inside = policy();
            let (during, nice) = foreground(|| (policy(), thread_nice()));
            assert_eq!((during, nice), (libc::SCHED_OTHER, Some(before)));
            assert_eq!(policy(), inside, "back in the background");
            drop(background);
            assert_eq!((policy(), thread_nice()), (libc::SCHED_OTHER, Some(before)));
        });
    }

    /// A solve in the background longer than it should starve computes 10 nicer instead, and
    /// still comes back to its priority after.
    #[test]
    fn a_starved_solve_computes_nicer_instead() {
        on_a_thread(|before, handle| {
            let Some(entered) = Entered::enter(handle, Duration::from_millis(20)) else {
                assert!(!restorable(), "entered wherever it can be undone");
                return;
            };
            let background = Background {
                entered: Some(entered),
            };
            let deadline = std::time::Instant::now() + Duration::from_secs(10);
            while policy() == libc::SCHED_IDLE {
                assert!(std::time::Instant::now() < deadline, "never moved");
                std::thread::sleep(Duration::from_millis(5));
            }
            assert_eq!(policy(), libc::SCHED_OTHER);
            assert_eq!(thread_nice(), Some((before + NICER_BY).min(19)));
            assert_eq!(foreground(thread_nice), Some(before));
            assert_eq!(
                thread_nice(),
                Some((before + NICER_BY).min(19)),
                "back nicer"
            );
            drop(background);
            assert_eq!(policy(), libc::SCHED_OTHER);
            assert_eq!(thread_nice(), Some(before));
        });
    }
}
