//! Two parts of an update run at once on two threads, or in turn when no thread can be had.

/// Runs `here` on this thread while `beside` runs on a second one, and returns both results.
/// When the process cannot start a thread (at its limit), they run one after the other on this
/// thread: the same results, only later, instead of a panic in the middle of an update. A
/// panic in `beside` is raised again here.
pub(super) fn run_beside<A, B: Send>(
    here: impl FnOnce() -> A,
    mut beside: impl FnMut() -> B + Send,
) -> (A, B) {
    let mut here = Some(here);
    let together = std::thread::scope(|scope| {
        // `beside` is lent, not given: if the thread cannot start, it is still ours to run.
        let helper = std::thread::Builder::new()
            .name("factord-beside".into())
            .spawn_scoped(scope, &mut beside)
            .ok()?;
        let a = here
            .take()
            .expect("`here` not run before the thread started")();
        let b = helper
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
        Some((a, b))
    });
    together.unwrap_or_else(|| {
        let here = here
            .take()
            .expect("`here` not run: the thread did not start");
        (here(), beside())
    })
}

#[cfg(test)]
mod tests {
    use super::run_beside;

    #[test]
    fn both_run_and_each_result_comes_back_to_its_side() {
        // Two different results of different types, each known without the helper.
        let data: Vec<u64> = (1..=1000).collect();
        let (sum, sevens) = run_beside(
            || data.iter().sum::<u64>(),
            || data.iter().filter(|&&v| v % 7 == 0).count(),
        );
        assert_eq!(sum, 500_500);
        assert_eq!(sevens, 142);
    }

    #[test]
    fn the_second_thread_is_another_thread() {
        let here = std::thread::current().id();
        let (a, b) = run_beside(
            || std::thread::current().id(),
            || std::thread::current().id(),
        );
        assert_eq!(a, here);
        assert_ne!(b, here);
    }

    #[test]
    #[should_panic(expected = "beside failed")]
    fn a_panic_beside_is_raised_here() {
        let _ = run_beside(|| 1, || -> u32 { panic!("beside failed") });
    }
}
