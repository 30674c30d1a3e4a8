//! `Service`: the factord service in this process, reached through its one command API (the
//! API HTTP and zenoh are adapters over; this is a third, for Python). A command is the JSON a
//! zenoh `rpc` carries (`{"op": "apply_batch", "session": …, "batch": …}`), its answer the
//! reply's JSON, a refusal a `ServiceError` carrying the error body a server sends (status,
//! code, message, field). Sessions live in memory; `factord.IncrementalSession`
//! (python/factord/session.py) is the session-shaped wrapper over it.

use std::sync::Arc;

use pyo3::prelude::*;

use factord::service::{
    parse_command, Caller, Limits, Recording, Service as LibraryService,
    ServiceError as LibraryServiceError,
};

use crate::errors::FactordError;

pyo3::create_exception!(
    _native,
    ServiceError,
    FactordError,
    "A command the service refused: `status` (HTTP-equivalent), `code`, `message`, `field` (where in the command, or None), as a server's error body."
);

/// The service with its own runtime and worker pool.
#[pyclass(module = "factord", name = "Service", frozen)]
pub struct Service {
    runtime: tokio::runtime::Runtime,
    service: Arc<LibraryService>,
    max_items: usize,
}

fn refused(py: Python<'_>, e: LibraryServiceError) -> PyErr {
    let body = &e.body;
    let error = ServiceError::new_err(format!(
        "{} {}: {}{}",
        body.status,
        body.code,
        body.message,
        body.field
            .as_deref()
            .map(|f| format!(" (at {f})"))
            .unwrap_or_default()
    ));
    let value = error.value(py);
    let _ = value.setattr("status", body.status);
    let _ = value.setattr("code", body.code.as_str());
    let _ = value.setattr("message", body.message.as_str());
    let _ = value.setattr("field", body.field.as_deref());
    error
}

#[pymethods]
impl Service {
    /// A service in this process: `workers` solver threads (default: one per core).
    #[new]
    #[pyo3(signature = (workers = None))]
    fn new(workers: Option<usize>) -> PyResult<Self> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("factord-python")
            .enable_all()
            .build()
            .map_err(|e| {
                FactordError::new_err(format!("cannot start the service's runtime: {e}"))
            })?;
        let defaults = Limits::default();
        let limits = Limits {
            workers: workers.unwrap_or(defaults.workers).max(1),
            ..defaults
        };
        let max_items = limits.max_batch_items;
        let service = runtime.block_on(async { LibraryService::new(limits) });
        Ok(Self {
            runtime,
            service,
            max_items,
        })
    }

    /// Runs one command (its JSON text) and answers the reply's JSON text; waits for it (a
    /// batch or optimize with `wait`, too) without holding the GIL.
    fn execute(&self, py: Python<'_>, command_json: &str) -> PyResult<String> {
        let command =
            parse_command(command_json.as_bytes(), self.max_items).map_err(|e| refused(py, e))?;
        let (runtime, service) = (&self.runtime, &self.service);
        let reply = py.detach(|| {
            runtime.block_on(service.execute(&Caller::Trusted, command, Recording::History))
        });
        let reply = reply.map_err(|e| refused(py, e))?;
        serde_json::to_string(&reply)
            .map_err(|e| FactordError::new_err(format!("the reply could not be written: {e}")))
    }
}

/// Registers the class and its exception.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Service>()?;
    m.add("ServiceError", m.py().get_type::<ServiceError>())?;
    Ok(())
}
