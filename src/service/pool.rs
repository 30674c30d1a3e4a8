//! The worker pool: a fixed number of OS threads running solves and batch jobs from one FIFO.
//!
//! Fairness comes from the queue discipline rather than priorities: a session is queued at most
//! once at a time (updates that arrive meanwhile are coalesced into its next solve), and a solve
//! that has run for a time slice while others wait yields and requeues at the back. So a huge
//! problem delays a small session by at most one slice per worker, never indefinitely.
//! The queue is bounded by construction (one entry per session plus at most `max_jobs` jobs).

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

pub type Task = Box<dyn FnOnce() + Send>;

/// How long a solve may hold a worker while others wait before it yields (it resumes where it
/// stopped, at the back of the queue).
pub const TIME_SLICE: Duration = Duration::from_millis(200);

struct Shared {
    queue: Mutex<VecDeque<Task>>,
    ready: Condvar,
    stopping: AtomicBool,
    busy: AtomicUsize,
    idle: Condvar,
}

/// A cheap handle tasks use to submit work and to ask whether they should yield.
#[derive(Clone)]
pub struct PoolHandle {
    shared: Arc<Shared>,
}

impl PoolHandle {
    /// Queues a task; `false` when the pool is shutting down.
    pub fn submit(&self, task: Task) -> bool {
        if self.is_stopping() {
            return false;
        }
        self.shared
            .queue
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .push_back(task);
        self.shared.ready.notify_one();
        true
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
        let dropped: Vec<Task> = shared
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
        let task = {
            let mut queue = shared.queue.lock().unwrap_or_else(|p| p.into_inner());
            loop {
                if shared.stopping.load(Ordering::SeqCst) {
                    return;
                }
                if let Some(task) = queue.pop_front() {
                    shared.busy.fetch_add(1, Ordering::SeqCst);
                    break task;
                }
                queue = shared.ready.wait(queue).unwrap_or_else(|p| p.into_inner());
            }
        };
        // A panicking task is a bug; it must not take the worker down with it.
        let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(task));
        if outcome.is_err() {
            tracing::error!("a pool task panicked");
        }
        let _guard = shared.queue.lock().unwrap_or_else(|p| p.into_inner());
        shared.busy.fetch_sub(1, Ordering::SeqCst);
        shared.idle.notify_all();
    }
}
