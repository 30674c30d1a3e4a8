//! The session's lock, counting who waits for it, so that work that holds it in slices (a
//! landing writing a large correction into the mirror, `provisional/landing.rs`) lets them go
//! first between its slices. A `std` mutex is not fair: a thread that unlocks and locks again
//! at once keeps it, while the thread it woke is still being scheduled (measured on the 3D
//! garage stream: seven slices of a landing in a row, the provisional answer waiting for all).

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Mutex, MutexGuard, TryLockError};
use std::time::{Duration, Instant};

/// How long [`StateLock::let_waiters_in`] waits at most for the waiters to take the lock:
/// longer than a woken thread takes to run, short against a slice.
const LET_IN_AT_MOST: Duration = Duration::from_micros(300);

#[derive(Debug)]
pub(super) struct StateLock<T> {
    inner: Mutex<T>,
    /// Threads blocked in [`StateLock::lock`].
    waiting: AtomicUsize,
}

impl<T> StateLock<T> {
    pub fn new(value: T) -> Self {
        Self {
            inner: Mutex::new(value),
            waiting: AtomicUsize::new(0),
        }
    }

    pub fn lock(&self) -> MutexGuard<'_, T> {
        // A panic while holding the lock would be a bug; the state is still consistent at every
        // await-free step, so keep serving.
        match self.inner.try_lock() {
            Ok(guard) => guard,
            Err(TryLockError::Poisoned(p)) => p.into_inner(),
            Err(TryLockError::WouldBlock) => {
                self.waiting.fetch_add(1, Ordering::SeqCst);
                let guard = self.inner.lock().unwrap_or_else(|p| p.into_inner());
                self.waiting.fetch_sub(1, Ordering::SeqCst);
                guard
            }
        }
    }

    /// Called with the lock released between two slices of work: returns once every thread
    /// that was waiting for the lock has taken it (or after [`LET_IN_AT_MOST`]).
    pub fn let_waiters_in(&self) {
        let start = Instant::now();
        while self.waiting.load(Ordering::SeqCst) > 0 && start.elapsed() < LET_IN_AT_MOST {
            std::thread::yield_now();
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;

    /// A holder that works in slices lets a waiting thread in between them: the waiter gets the
    /// lock before the holder's last slice, which it would not with a plain relock.
    #[test]
    fn a_thread_waiting_gets_the_lock_between_slices() {
        let lock = Arc::new(StateLock::new(Vec::<&str>::new()));
        let guard = lock.lock();
        let waiter = {
            let lock = Arc::clone(&lock);
            std::thread::spawn(move || lock.lock().push("waiter"))
        };
        while lock.waiting.load(Ordering::SeqCst) == 0 {
            std::thread::yield_now();
        }
        drop(guard);
        for _ in 0..3 {
            lock.let_waiters_in();
            let mut slice = lock.lock();
            slice.push("slice");
            std::thread::sleep(Duration::from_millis(2));
        }
        waiter.join().unwrap();
        assert_eq!(lock.lock()[0], "waiter", "{:?}", lock.lock());
    }
}
