//! A control for tail latency on a shared machine: a thread that asks to sleep 1 ms, over and
//! over, and records how late it wakes up. What it sees late, any process here (the servers,
//! the robots) sees late too; an ack tail of the same size as its tail is the machine's.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serde_json::{json, Value};

pub struct Jitter {
    stop: Arc<AtomicBool>,
    thread: JoinHandle<Vec<f64>>,
}

impl Jitter {
    pub fn start() -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let flag = stop.clone();
        let thread = std::thread::spawn(move || {
            let mut late_ms = Vec::new();
            while !flag.load(Ordering::Relaxed) {
                let t = Instant::now();
                std::thread::sleep(Duration::from_millis(1));
                late_ms.push((t.elapsed().as_secs_f64() - 1e-3).max(0.0) * 1e3);
            }
            late_ms
        });
        Self { stop, thread }
    }

    /// Stops the probe: how late its wake-ups were (ms): p50, p99, worst, and how many were
    /// more than 20 ms late.
    pub fn finish(self) -> Value {
        self.stop.store(true, Ordering::Relaxed);
        let mut late = self.thread.join().unwrap_or_default();
        let over_20 = late.iter().filter(|&&v| v > 20.0).count();
        let (p50, p99, worst) = crate::acks::summary(&mut late);
        json!({"wakeups": late.len(), "late_p50_ms": p50, "late_p99_ms": p99,
               "late_worst_ms": worst, "late_over_20ms": over_20})
    }
}
