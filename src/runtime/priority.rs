//! Solves and batch jobs are throughput work; the request path (the HTTP and zenoh threads,
//! the journal's fsync, provisional answers) is latency work. The threads that run the former
//! lower their own scheduling priority, so that on a busy core the latter preempt them at once
//! instead of waiting out a time slice.
//!
//! Measured on the 100 000-pose stream with a 20 ms budget (2 cores, issue 55): with the exact
//! solve keeping one core busy, provisional answers and acknowledgements stalled 3–4 ms at a
//! time in arbitrary steps (copying 300 values, publishing them), the kernel's slice, and the
//! p99 of updates at 100k was twice that at 10k, where exact solves leave the cores idle.

/// How much nicer than the process a worker thread runs (Linux nice values; 19 is the
/// lowest priority). At 10 a thread's CPU weight is about a tenth of a default thread's, yet
/// it still takes every cycle the request path leaves idle.
pub const WORKER_NICENESS: i32 = 10;

/// Lowers the calling thread's priority by [`WORKER_NICENESS`] (at most to 19); threads it
/// starts inherit it. Best effort: where it cannot (another OS), the thread keeps its priority.
pub fn lower_this_thread() {
    #[cfg(target_os = "linux")]
    // SAFETY: gettid has no preconditions; getpriority and setpriority only read and change
    // the scheduling priority of the calling thread (Linux: PRIO_PROCESS with a thread id).
    unsafe {
        let tid = libc::gettid() as libc::id_t;
        let current = libc::getpriority(libc::PRIO_PROCESS, tid);
        let _ = libc::setpriority(libc::PRIO_PROCESS, tid, (current + WORKER_NICENESS).min(19));
    }
}

/// The calling thread's nice value (Linux; 0 elsewhere).
pub fn this_thread_niceness() -> i32 {
    #[cfg(target_os = "linux")]
    // SAFETY: as in `lower_this_thread`, only reads.
    unsafe {
        libc::getpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t)
    }
    #[cfg(not(target_os = "linux"))]
    0
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    use super::*;

    #[test]
    fn a_lowered_thread_is_nicer_than_its_parent_and_passes_it_on() {
        let parent = this_thread_niceness();
        let (own, child) = std::thread::spawn(|| {
            lower_this_thread();
            let own = this_thread_niceness();
            let child = std::thread::spawn(this_thread_niceness).join().unwrap();
            (own, child)
        })
        .join()
        .unwrap();
        assert_eq!(own, (parent + WORKER_NICENESS).min(19));
        assert_eq!(child, own, "threads a worker starts inherit its niceness");
        assert_eq!(this_thread_niceness(), parent, "the caller's thread only");
    }
}
