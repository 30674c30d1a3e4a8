//! The worker pool: a fixed number of OS threads running solves and batch jobs from one FIFO.
//!
//! Fairness comes from the queue discipline rather than priorities: a session is queued at most
//! once at a time (updates that arrive meanwhile are coalesced into its next solve), and a solve
//! that has run for a time slice while others wait yields and requeues at the back. So a huge
//! problem delays a small session by at most one slice per worker, never indefinitely.
//! The queue is bounded by construction (one entry per session plus at most `max_jobs` jobs).
//!
//! Batch jobs run on threads of their own but compute only during a *turn* a worker lends them
//! ([`PoolHandle::lend_turn`]): the lending worker blocks, so the pool's concurrency is unchanged,
//! and a job gives its turn back at any of the solver's fine-grained checkpoints without losing
//! its state (factorisations, buffers), then queues for the next one. With two workers or more,
//! jobs are lent at most `workers - 1` turns at once: one worker always serves sessions, so a
//! session's small solve never waits behind giant jobs, even behind a factorisation that cannot
//! be interrupted.
//!
//! A solve may also borrow idle workers' cores for threads of its own
//! ([`PoolHandle::borrow_idle`]): only while nothing waits, and a borrowed worker takes no task
//! until the cores are given back, so the pool's concurrency is unchanged there too.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{mpsc, Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

pub type Task = Box<dyn FnOnce() + Send>;

/// How long a solve may hold a worker while others wait before it yields (it resumes where it
/// stopped, at the back of the queue).
pub const TIME_SLICE: Duration = Duration::from_millis(200);

/// A queued task; `lent` marks a turn lent to a job, which counts against `max_lent`.
struct Queued {
    task: Task,
    lent: bool,
}

struct Shared {
    queue: Mutex<VecDeque<Queued>>,
    ready: Condvar,
    stopping: AtomicBool,
    busy: AtomicUsize,
    idle: Condvar,
    /// Turns lent to jobs now, and how many may be at once (changed under the queue's lock).
    lent: AtomicUsize,
    max_lent: usize,
    /// Idle workers whose cores a solve borrowed (changed under the queue's lock): they take no
    /// task until given back.
    borrowed: AtomicUsize,
    workers: usize,
}

/// A cheap handle tasks use to submit work and to ask whether they should yield.
#[derive(Clone)]
pub struct PoolHandle {
    shared: Arc<Shared>,
}

impl PoolHandle {
    /// Queues a task; `false` when the pool is shutting down.
    pub fn submit(&self, task: Task) -> bool {
        self.enqueue(Queued { task, lent: false })
    }

    fn enqueue(&self, entry: Queued) -> bool {
        if self.is_stopping() {
            return false;
        }
        let lent = entry.lent;
        self.shared
            .queue
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .push_back(entry);
        // A task any worker may run wakes one: waking every idle worker for it made the others
        // wake, find nothing and sleep again, a context switch per solve on the cores the
        // request's own threads need. A lent turn wakes all, as it may be the only runnable
        // entry for a worker other than the one woken.
        match lent {
            false => self.shared.ready.notify_one(),
            true => self.shared.ready.notify_all(),
        }
        true
    }

    /// Blocks the calling thread (not a worker) until a worker lends it a turn, in queue order
    /// with the other tasks; `None` when the pool is shutting down (or shut down meanwhile).
    pub fn lend_turn(&self) -> Option<Turn> {
        let (go, granted) = mpsc::sync_channel::<mpsc::Sender<()>>(1);
        let task: Task = Box::new(move || {
            let (end, ended) = mpsc::channel::<()>();
            if go.send(end).is_ok() {
                // The worker waits here, idle, until the turn is dropped.
                let _ = ended.recv();
            }
        });
        if !self.enqueue(Queued { task, lent: true }) {
            return None;
        }
        // A task dropped unrun (shutdown) drops `go`: the wait ends with an error.
        let end = granted.recv().ok()?;
        Some(Turn {
            pool: self.clone(),
            _end: end,
            started: Instant::now(),
        })
    }

    /// Tasks waiting for a worker.
    pub fn waiting(&self) -> usize {
        self.shared
            .queue
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .len()
    }

    pub fn busy(&self) -> usize {
        self.shared.busy.load(Ordering::SeqCst)
    }

    pub fn is_stopping(&self) -> bool {
        self.shared.stopping.load(Ordering::SeqCst)
    }

    /// The pool's size.
    pub fn workers(&self) -> usize {
        self.shared.workers
    }

    /// Borrows up to `wanted` idle workers' cores for threads of the calling task's own (a
    /// solve on more than one thread): none while a task waits for a worker, never more than
    /// the workers that are idle. The borrowed workers take no task until the [`Borrowed`] is
    /// dropped.
    pub fn borrow_idle(&self, wanted: usize) -> Borrowed {
        let shared = &self.shared;
        let queue = shared.queue.lock().unwrap_or_else(|p| p.into_inner());
        let occupied = shared.busy.load(Ordering::SeqCst) + shared.borrowed.load(Ordering::SeqCst);
        let count = if queue.is_empty() {
            wanted.min(shared.workers.saturating_sub(occupied))
        } else {
            0
        };
        shared.borrowed.fetch_add(count, Ordering::SeqCst);
        Borrowed {
            pool: self.clone(),
            count,
        }
    }
}

/// Idle workers' cores borrowed by a task ([`PoolHandle::borrow_idle`]); dropping it gives them
/// back.
pub struct Borrowed {
    pool: PoolHandle,
    count: usize,
}

impl Borrowed {
    /// How many cores were borrowed (0: the task runs on its own worker alone).
    pub fn count(&self) -> usize {
        self.count
    }
}

impl Drop for Borrowed {
    fn drop(&mut self) {
        if self.count == 0 {
            return;
        }
        let shared = &self.pool.shared;
        let _queue = shared.queue.lock().unwrap_or_else(|p| p.into_inner());
        shared.borrowed.fetch_sub(self.count, Ordering::SeqCst);
        // Tasks queued meanwhile may run now.
        shared.ready.notify_all();
    }
}

/// A worker's turn lent to a job's thread (see [`PoolHandle::lend_turn`]); dropping it gives
/// the worker back.
pub struct Turn {
    pool: PoolHandle,
    /// Dropping it wakes the lending worker.
    _end: mpsc::Sender<()>,
    started: Instant,
}

impl Turn {
    /// How long this turn has been held.
    pub fn held(&self) -> Duration {
        self.started.elapsed()
    }

    /// Whether to give the turn back: held for a time slice while other work waits.
    pub fn should_yield(&self) -> bool {
        self.held() > TIME_SLICE && self.pool.waiting() > 0
    }

    /// Gives the worker back and queues for another turn (at the back, behind the work that was
    /// waiting). `None` when the pool shuts down meanwhile.
    pub fn requeue(self) -> Option<Turn> {
        let pool = self.pool.clone();
        drop(self);
        pool.lend_turn()
    }
}

pub struct WorkerPool {
    handle: PoolHandle,
    threads: Mutex<Vec<JoinHandle<()>>>,
    pub workers: usize,
}

impl WorkerPool {
    pub fn new(workers: usize) -> Self {
        let shared = Arc::new(Shared {
            queue: Mutex::new(VecDeque::new()),
            ready: Condvar::new(),
            stopping: AtomicBool::new(false),
            busy: AtomicUsize::new(0),
            idle: Condvar::new(),
            lent: AtomicUsize::new(0),
            // One worker stays for sessions when there is more than one.
            max_lent: workers.saturating_sub(1).max(1),
            borrowed: AtomicUsize::new(0),
            workers,
        });
        let threads = (0..workers)
            .map(|i| {
                let shared = Arc::clone(&shared);
                std::thread::Builder::new()
                    .name(format!("factord-worker-{i}"))
                    .spawn(move || worker(&shared))
                    .expect("spawning a worker thread")
            })
            .collect();
        Self {
            handle: PoolHandle { shared },
            threads: Mutex::new(threads),
            workers,
        }
    }

    pub fn handle(&self) -> PoolHandle {
        self.handle.clone()
    }

    /// Stops taking work, lets running tasks see `is_stopping` (solves stop after their current
    /// iteration), drops queued tasks, and joins the workers (waiting at most `timeout`).
    pub fn shutdown(&self, timeout: Duration) {
        let shared = &self.handle.shared;
        shared.stopping.store(true, Ordering::SeqCst);
        let dropped: Vec<Queued> = shared
            .queue
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .drain(..)
            .collect();
        drop(dropped);
        shared.ready.notify_all();
        let deadline = Instant::now() + timeout;
        let mut queue = shared.queue.lock().unwrap_or_else(|p| p.into_inner());
        while shared.busy.load(Ordering::SeqCst) > 0 && Instant::now() < deadline {
            queue = shared
                .idle
                .wait_timeout(queue, deadline - Instant::now())
                .map(|(q, _)| q)
                .unwrap_or_else(|p| p.into_inner().0);
        }
        drop(queue);
        if shared.busy.load(Ordering::SeqCst) == 0 {
            for t in self
                .threads
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .drain(..)
            {
                let _ = t.join();
            }
        }
    }
}

fn worker(shared: &Shared) {
    loop {
        let entry = {
            let mut queue = shared.queue.lock().unwrap_or_else(|p| p.into_inner());
            loop {
                if shared.stopping.load(Ordering::SeqCst) {
                    return;
                }
                // The first entry that may run: a lent turn waits while jobs hold `max_lent`;
                // nothing runs on a worker whose core is borrowed.
                let lend_allowed = shared.lent.load(Ordering::SeqCst) < shared.max_lent;
                let free = shared.busy.load(Ordering::SeqCst)
                    + shared.borrowed.load(Ordering::SeqCst)
                    < shared.workers;
                let first = queue.iter().position(|q| !q.lent || lend_allowed);
                if let Some(at) = first.filter(|_| free) {
                    let entry = queue.remove(at).expect("position is in the queue");
                    shared.busy.fetch_add(1, Ordering::SeqCst);
                    if entry.lent {
                        shared.lent.fetch_add(1, Ordering::SeqCst);
                    }
                    break entry;
                }
                queue = shared.ready.wait(queue).unwrap_or_else(|p| p.into_inner());
            }
        };
        // A panicking task is a bug; it must not take the worker down with it.
        let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(entry.task));
        if outcome.is_err() {
            tracing::error!("a pool task panicked");
        }
        let _guard = shared.queue.lock().unwrap_or_else(|p| p.into_inner());
        shared.busy.fetch_sub(1, Ordering::SeqCst);
        if entry.lent {
            shared.lent.fetch_sub(1, Ordering::SeqCst);
            // A lent turn queued behind the cap may run now.
            shared.ready.notify_all();
        }
        shared.idle.notify_all();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A task that reports on `done` when it runs.
    fn reporting(done: &mpsc::Sender<()>) -> Task {
        let done = done.clone();
        Box::new(move || {
            let _ = done.send(());
        })
    }

    #[test]
    fn borrowed_cores_are_idle_workers_and_run_nothing_until_given_back() {
        let pool = WorkerPool::new(2);
        let handle = pool.handle();
        let (done, ran) = mpsc::channel();
        // From a task on one worker: the other one is idle, and only it can be borrowed.
        let (report, borrowed_count) = mpsc::channel();
        let (release, released) = mpsc::channel::<()>();
        let inner = handle.clone();
        assert!(handle.submit(Box::new(move || {
            let borrowed = inner.borrow_idle(8);
            let _ = report.send(borrowed.count());
            let _ = released.recv();
            drop(borrowed);
        })));
        assert_eq!(borrowed_count.recv().unwrap(), 1);
        // Both workers are taken (one running, one lent): a new task waits.
        assert!(handle.submit(reporting(&done)));
        assert!(ran.recv_timeout(Duration::from_millis(200)).is_err());
        // While it waits, nothing more is lent.
        assert_eq!(handle.borrow_idle(1).count(), 0);
        release.send(()).unwrap();
        ran.recv_timeout(Duration::from_secs(5))
            .expect("the task runs once the cores are given back");
        pool.shutdown(Duration::from_secs(5));
    }

    #[test]
    fn an_idle_pool_lends_at_most_its_workers_and_a_task_runs_after_the_drop() {
        let pool = WorkerPool::new(3);
        let handle = pool.handle();
        let borrowed = handle.borrow_idle(usize::MAX);
        assert_eq!(borrowed.count(), 3);
        assert_eq!(handle.borrow_idle(1).count(), 0);
        let (done, ran) = mpsc::channel();
        assert!(handle.submit(reporting(&done)));
        assert!(ran.recv_timeout(Duration::from_millis(200)).is_err());
        drop(borrowed);
        ran.recv_timeout(Duration::from_secs(5))
            .expect("runs after the drop");
        assert_eq!(handle.borrow_idle(0).count(), 0);
        pool.shutdown(Duration::from_secs(5));
    }
}
