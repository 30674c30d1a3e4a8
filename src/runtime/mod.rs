//! What every session and the service share in one process: the worker pool solves and jobs run
//! on, and the metrics they record.
//!
//! Layer 7, beside `journal`: imports `api` (error bodies for metrics) and nothing above. It sits
//! below the session rather than above the service because both submit work to the pool and record
//! metrics; what starts the process (tokio, listeners, config) is the composition root
//! (`server`, `cli`) at the top.

pub mod metrics;
pub mod pool;
