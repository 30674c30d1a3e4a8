//! Summary statistics of the bench binaries' samples, shared by including this file
//! (`#[path = "../stats.rs"] mod stats;`), so every bench reports medians and percentiles the
//! same way.
#![allow(dead_code)]

/// The median of `samples` (the upper one of an even count); sorts them. NaN when empty.
pub fn median(samples: &mut [f64]) -> f64 {
    samples.sort_by(f64::total_cmp);
    samples.get(samples.len() / 2).copied().unwrap_or(f64::NAN)
}

/// The `p`-quantile (0 ≤ p ≤ 1) of ascending `sorted` samples, nearest rank. NaN when empty.
pub fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((sorted.len() as f64 - 1.0) * p).round() as usize]
}

/// The `p`-quantile of ascending `sorted` samples, interpolated linearly between the closest
/// ranks (numpy's default, which the Python reference harnesses report). NaN when empty.
pub fn percentile_interpolated(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let pos = (sorted.len() as f64 - 1.0) * p;
    let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
    sorted[lo] + (sorted[hi] - sorted[lo]) * (pos - lo as f64)
}
