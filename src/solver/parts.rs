//! What the solver's threaded passes share: a pass cuts its work into parts, runs the first
//! on the calling thread (which checks the budget) and the others on scoped threads, then
//! gathers their results in part order.

use std::ops::ControlFlow;
use std::thread::ScopedJoinHandle;

/// The calling thread's result first, then every spawned part's in spawn order (a part's panic
/// is resumed here).
pub(crate) fn mine_then_joined<T>(mine: T, others: Vec<ScopedJoinHandle<'_, T>>) -> Vec<T> {
    let mut results = Vec::with_capacity(others.len() + 1);
    results.push(mine);
    for other in others {
        results.push(
            other
                .join()
                .unwrap_or_else(|panic| std::panic::resume_unwind(panic)),
        );
    }
    results
}

/// The parts' chi2 summed in part order; a stop when any part stopped; the first error.
pub(crate) fn sum_of_parts<E>(
    results: Vec<Result<ControlFlow<(), f64>, E>>,
) -> Result<ControlFlow<(), f64>, E> {
    let mut total = 0.0;
    for result in results {
        match result? {
            ControlFlow::Continue(chi2) => total += chi2,
            ControlFlow::Break(()) => return Ok(ControlFlow::Break(())),
        }
    }
    Ok(ControlFlow::Continue(total))
}
