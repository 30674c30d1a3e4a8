//! Quantiles of the χ² distribution: the squared whitened error of a correct measurement with
//! `d` residual components is χ²(d)-distributed, so its `confidence` quantile is the threshold
//! beyond which a measurement is more likely wrong than unlucky. Graduated non-convexity takes
//! its truncation threshold from here, which is what frees the user from choosing a scale.

/// [`chi_square_quantile`], computed once per (dof, confidence) for the process: a bisection
/// costs a few hundred microseconds, and the deciders ask for the same few thresholds for every
/// factor they weigh (a streamed closure's gate, every pair of a merge's consensus, every
/// candidate of graduated non-convexity).
pub fn cached_quantile(dof: usize, confidence: f64) -> f64 {
    use std::collections::HashMap;
    use std::sync::{Mutex, OnceLock};
    static CACHE: OnceLock<Mutex<HashMap<(usize, u64), f64>>> = OnceLock::new();
    let cache = CACHE.get_or_init(Mutex::default);
    let key = (dof, confidence.to_bits());
    if let Some(&q) = cache.lock().unwrap_or_else(|p| p.into_inner()).get(&key) {
        return q;
    }
    let q = chi_square_quantile(dof, confidence);
    cache
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .insert(key, q);
    q
}

/// The `confidence` quantile of χ² with `dof` degrees of freedom (`0 < confidence < 1`).
pub fn chi_square_quantile(dof: usize, confidence: f64) -> f64 {
    let a = dof.max(1) as f64 / 2.0;
    // P(a, x/2) is increasing in x: bisection on a bracket that grows until it holds the quantile.
    let (mut low, mut high) = (0.0_f64, 2.0 * a + 10.0);
    while lower_regularized_gamma(a, high / 2.0) < confidence {
        low = high;
        high *= 2.0;
    }
    for _ in 0..200 {
        let mid = 0.5 * (low + high);
        if lower_regularized_gamma(a, mid / 2.0) < confidence {
            low = mid;
        } else {
            high = mid;
        }
        if high - low <= 1e-12 * high {
            break;
        }
    }
    0.5 * (low + high)
}

/// P(a, x) = γ(a, x) / Γ(a): by its power series below `a + 1`, by the continued fraction of
/// the upper part above (each converges fast on its side).
fn lower_regularized_gamma(a: f64, x: f64) -> f64 {
    if x <= 0.0 {
        return 0.0;
    }
    let log_prefactor = a * x.ln() - x - ln_gamma(a);
    if x < a + 1.0 {
        let (mut term, mut sum, mut n) = (1.0 / a, 1.0 / a, a);
        for _ in 0..1000 {
            n += 1.0;
            term *= x / n;
            sum += term;
            if term.abs() < sum.abs() * 1e-16 {
                break;
            }
        }
        sum * log_prefactor.exp()
    } else {
        // Modified Lentz evaluation of the continued fraction for Q(a, x).
        let tiny = 1e-300;
        let mut b = x + 1.0 - a;
        let mut c = 1.0 / tiny;
        let mut d = 1.0 / b;
        let mut h = d;
        for i in 1..1000 {
            let an = -(i as f64) * (i as f64 - a);
            b += 2.0;
            d = an * d + b;
            if d.abs() < tiny {
                d = tiny;
            }
            c = b + an / c;
            if c.abs() < tiny {
                c = tiny;
            }
            d = 1.0 / d;
            let step = d * c;
            h *= step;
            if (step - 1.0).abs() < 1e-16 {
                break;
            }
        }
        1.0 - log_prefactor.exp() * h
    }
}

/// ln Γ(x) for x > 0 (Lanczos, g = 7, nine terms: about 15 significant digits).
fn ln_gamma(x: f64) -> f64 {
    const COEFFICIENTS: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        // Reflection: Γ(x) Γ(1 − x) = π / sin(πx).
        let pi = std::f64::consts::PI;
        return (pi / (pi * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut sum = COEFFICIENTS[0];
    for (i, c) in COEFFICIENTS.iter().enumerate().skip(1) {
        sum += c / (x + i as f64);
    }
    let t = x + 7.5;
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + sum.ln()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Values from standard tables (R's `qchisq`).
    #[test]
    fn quantiles_match_the_tables() {
        for (dof, confidence, expected) in [
            (1, 0.99, 6.634_896_601),
            (2, 0.99, 9.210_340_372),
            (3, 0.99, 11.344_866_73),
            (6, 0.99, 16.811_893_83),
            (3, 0.95, 7.814_727_903),
            (6, 0.999, 22.457_744_48),
        ] {
            let q = chi_square_quantile(dof, confidence);
            assert!(
                (q - expected).abs() < 1e-6 * expected,
                "dof {dof} confidence {confidence}: {q} vs {expected}"
            );
        }
    }
}
