//! The two GNC surrogates of Yang, Antonante, Tzoumas and Carlone ("Graduated Non-Convexity for
//! Robust Spatial Perception", RA-L 2020), on errors normalised by their threshold: `r = s / c̄²`
//! with `s` the squared whitened error, so that `r > 1` means "beyond the χ² quantile". Each
//! surrogate starts (small μ for TLS, large μ for Geman-McClure) close to plain least squares,
//! where every measurement counts, and moves towards the robust cost one step of μ at a time.

use serde::{Deserialize, Serialize};

/// How much μ moves per outer iteration (the paper's and GTSAM's default factor).
const MU_STEP: f64 = 1.4;

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum GncKernel {
    /// Truncated least squares: ρ(r) = min(r, 1). Ends with every weight 0 or 1, so the result is
    /// exactly the least-squares optimum of the measurements it kept.
    #[default]
    Tls,
    /// Geman-McClure: ρ(r) = r / (1 + r) at μ = 1.
    GemanMcclure,
}

impl GncKernel {
    pub fn parse(text: &str) -> Option<Self> {
        match text.to_ascii_lowercase().replace('-', "_").as_str() {
            "tls" | "truncated_least_squares" => Some(Self::Tls),
            "gm" | "geman_mcclure" => Some(Self::GemanMcclure),
            _ => None,
        }
    }

    /// μ at which the surrogate is convex over errors up to `max_ratio` (the largest normalised
    /// error at the start), so the first weighted solve is as benign as least squares.
    pub fn initial_mu(self, max_ratio: f64) -> f64 {
        match self {
            Self::Tls => 1.0 / (2.0 * max_ratio - 1.0).max(1e-12),
            Self::GemanMcclure => (2.0 * max_ratio).max(1.0),
        }
    }

    /// The next μ, one step towards the robust cost.
    pub fn next_mu(self, mu: f64) -> f64 {
        match self {
            Self::Tls => mu * MU_STEP,
            Self::GemanMcclure => (mu / MU_STEP).max(1.0),
        }
    }

    /// The weight that minimises the surrogate's Black-Rangarajan dual for normalised error `r`.
    pub fn weight(self, mu: f64, r: f64) -> f64 {
        match self {
            Self::Tls => {
                if r >= (mu + 1.0) / mu {
                    0.0
                } else if r <= mu / (mu + 1.0) {
                    1.0
                } else {
                    ((mu * (mu + 1.0) / r).sqrt() - mu).clamp(0.0, 1.0)
                }
            }
            Self::GemanMcclure => {
                let q = mu / (mu + r);
                q * q
            }
        }
    }

    /// Whether the graduation is over after a solve with `weights` at `mu`: TLS once every weight
    /// is (within `tolerance`) 0 or 1, Geman-McClure once μ reached 1.
    pub fn converged(self, mu: f64, weights: &[f64], tolerance: f64) -> bool {
        match self {
            Self::Tls => weights
                .iter()
                .all(|&w| w <= tolerance || w >= 1.0 - tolerance),
            Self::GemanMcclure => mu <= 1.0,
        }
    }

    /// Whether a measurement of normalised error `r` (at the end, weight `w`) is kept.
    pub fn keeps(self, r: f64, w: f64) -> bool {
        match self {
            Self::Tls => w >= 0.5,
            Self::GemanMcclure => r <= 1.0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tls_weights_are_least_squares_at_small_mu_and_binary_at_large_mu() {
        let k = GncKernel::Tls;
        let mu = k.initial_mu(100.0);
        // Every error up to the largest keeps a positive weight at the start.
        assert!(k.weight(mu, 100.0) > 0.0);
        assert!(k.weight(mu, 0.5) > k.weight(mu, 50.0));
        let big = 1e6;
        assert_eq!(k.weight(big, 0.99), 1.0);
        assert_eq!(k.weight(big, 1.01), 0.0);
        assert!(k.converged(big, &[0.0, 1.0], 1e-6));
        assert!(!k.converged(mu, &[0.5], 1e-6));
    }

    #[test]
    fn geman_mcclure_mu_decreases_to_one() {
        let k = GncKernel::GemanMcclure;
        let mut mu = k.initial_mu(50.0);
        let mut steps = 0;
        while !k.converged(mu, &[], 0.0) {
            mu = k.next_mu(mu);
            steps += 1;
        }
        assert_eq!(mu, 1.0);
        assert!(steps > 5 && steps < 30, "{steps}");
        assert!(k.weight(1.0, 0.1) > 0.8 && k.weight(1.0, 10.0) < 0.01);
    }
}
