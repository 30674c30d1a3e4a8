//! Zeroed buffers the kernel may back with transparent huge pages. A bundle adjustment's H is
//! first written by the first linearisation: with 4 KiB pages every one costs a fault and a
//! cleared page (problem-16-22106: 19 MB, ~4 700 faults), 2 MiB pages cost 512 times fewer
//! faults. Where transparent huge pages are `madvise`-only (Debian's default), a region has to
//! ask for them; where they are `always` or `never` the advice changes nothing.

/// Buffers smaller than this stay on ordinary pages: two huge pages at least, so that the
/// advised region (the whole huge pages inside the buffer) is worth a system call.
const MIN_BYTES: usize = 4 << 20;
const HUGE_PAGE: usize = 2 << 20;

/// `len` zeros, their untouched pages advised to be huge (see the module documentation).
pub(crate) fn zeroed(len: usize) -> Vec<f64> {
    // A large zeroed allocation is fresh memory from the kernel, not yet touched: the advice
    // applies to every page the solve then writes.
    let buffer = vec![0.0; len];
    advise(&buffer);
    buffer
}

#[cfg(target_os = "linux")]
fn advise(buffer: &[f64]) {
    let bytes = std::mem::size_of_val(buffer);
    if bytes < MIN_BYTES {
        return;
    }
    let start = buffer.as_ptr() as usize;
    let (first, end) = (
        start.next_multiple_of(HUGE_PAGE),
        (start + bytes) / HUGE_PAGE * HUGE_PAGE,
    );
    if end > first {
        // SAFETY: the range lies inside the live allocation `buffer`; MADV_HUGEPAGE changes
        // neither the contents nor the validity of its pages, only how the kernel backs them.
        // Its failure (THP compiled out) leaves ordinary pages, which is fine.
        unsafe {
            libc::madvise(first as *mut libc::c_void, end - first, libc::MADV_HUGEPAGE);
        }
    }
}

#[cfg(not(target_os = "linux"))]
fn advise(_: &[f64]) {}

#[cfg(test)]
mod tests {
    #[test]
    fn zeroed_buffers_are_zeros_of_the_length_asked() {
        for len in [0, 1, 1000, 3 << 20] {
            let buffer = super::zeroed(len);
            assert_eq!(buffer.len(), len);
            assert!(buffer.iter().all(|&x| x == 0.0));
        }
    }
}
