//! Runtime dispatch to AVX2 + FMA code for the few hot loops (Schur elimination, per-factor
//! JᵀJ): the binary stays portable to any x86-64, and the compiler vectorises those loops with
//! 256-bit FMAs where the CPU has them.
//!
//! The pattern: an `#[inline(always)]` function holding the loops, a twin with
//! `#[target_feature(enable = "avx2,fma")]` that only calls it (so the loops are compiled into
//! the twin with those features), and a caller choosing the twin when [`has_wide_vectors`].
//! A closure would not do: it is not inlined into the feature-enabled function.
//!
//! 512-bit vectors only where written by hand: the Schur elimination's camera-pair update
//! (`schur::avx512`, a third twin chosen first on CPUs with AVX-512F). Letting the compiler use
//! them was measured on the Xeon of `BENCHMARKS.md`: enabling AVX-512 on the elimination loop
//! changed nothing, and on the linearisation loop it made linearisation twice as slow.

/// Whether this CPU runs the AVX2 + FMA variant (detected once, then a cached load).
#[inline]
pub fn has_wide_vectors() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}
