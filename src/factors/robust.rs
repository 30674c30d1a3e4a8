//! Robust kernels ρ(s) on the squared whitened error s = ‖r‖², and Triggs' correction.
//!
//! A factor's chi2 contribution becomes ρ(s). Linearising ρ(‖r + JΔ‖²) to second order gives
//! (Triggs et al., "Bundle adjustment — a modern synthesis", §4.3; the same scheme as Ceres'
//! `Corrector`) a rescaled residual and Jacobian:
//!
//! ```text
//! α = 1 − sqrt(1 + 2 s ρ''/ρ')   (α = 0 when ρ'' ≤ 0, i.e. plain IRLS)
//! r̃ = sqrt(ρ') / (1 − α) · r
//! J̃ = sqrt(ρ') · (I − α r rᵀ / s) · J
//! ```
//!
//! so that `J̃ᵀJ̃` and `J̃ᵀr̃` are the Gauss-Newton approximations of the kernel's Hessian and gradient.

use serde::{Deserialize, Serialize};

/// ρ and its first two derivatives with respect to s.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct KernelValue {
    pub rho: f64,
    pub rho1: f64,
    pub rho2: f64,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(tag = "kind", content = "scale", rename_all = "snake_case")]
pub enum RobustKernel {
    /// ρ(s) = s for s ≤ δ², 2δ√s − δ² beyond.
    Huber(f64),
    /// ρ(s) = δ² ln(1 + s/δ²).
    Cauchy(f64),
    /// Tukey's biweight: ρ(s) = δ²/3 (1 − (1 − s/δ²)³) for s ≤ δ², δ²/3 beyond (outliers get
    /// no weight at all).
    Tukey(f64),
    /// Geman-McClure: ρ(s) = δ² s / (δ² + s), bounded by δ².
    GemanMcclure(f64),
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum KernelParseError {
    #[error("unknown robust kernel `{0}` (expected huber, cauchy, tukey or geman_mcclure, as <name>:<scale>)")]
    Unknown(String),
    #[error("robust kernel scale `{0}` must be a number from 1e-9 to 1e9")]
    BadScale(String),
}

/// The smallest and largest robust-kernel scale accepted. δ² enters ρ and its derivatives, so a
/// scale whose square under- or overflows (1e-300, 1e300) makes the cost non-finite; a scale in
/// whitened units beyond these bounds has no use either.
pub const MIN_SCALE: f64 = 1e-9;
pub const MAX_SCALE: f64 = 1e9;

/// Whether `delta` is a scale a kernel is given: finite, from [`MIN_SCALE`] to [`MAX_SCALE`].
pub fn scale_in_range(delta: f64) -> bool {
    (MIN_SCALE..=MAX_SCALE).contains(&delta)
}

impl RobustKernel {
    /// Parses `huber:1.0`, `cauchy:0.5`, `tukey:4.685`, `geman_mcclure:1` (scale defaults to 1).
    pub fn parse(text: &str) -> Result<Self, KernelParseError> {
        let (name, scale) = text.split_once(':').unwrap_or((text, "1"));
        let delta: f64 = scale
            .parse()
            .map_err(|_| KernelParseError::BadScale(scale.into()))?;
        if !scale_in_range(delta) {
            return Err(KernelParseError::BadScale(scale.into()));
        }
        match name.to_ascii_lowercase().as_str() {
            "huber" => Ok(Self::Huber(delta)),
            "cauchy" => Ok(Self::Cauchy(delta)),
            "tukey" => Ok(Self::Tukey(delta)),
            "geman_mcclure" | "geman-mcclure" | "gm" => Ok(Self::GemanMcclure(delta)),
            _ => Err(KernelParseError::Unknown(name.into())),
        }
    }

    /// The scale δ (in whitened residual units).
    pub fn scale(&self) -> f64 {
        match *self {
            Self::Huber(d) | Self::Cauchy(d) | Self::Tukey(d) | Self::GemanMcclure(d) => d,
        }
    }

    pub fn evaluate(&self, s: f64) -> KernelValue {
        match *self {
            Self::Huber(delta) => {
                let d2 = delta * delta;
                if s <= d2 {
                    KernelValue {
                        rho: s,
                        rho1: 1.0,
                        rho2: 0.0,
                    }
                } else {
                    let r = s.sqrt();
                    KernelValue {
                        rho: 2.0 * delta * r - d2,
                        rho1: delta / r,
                        rho2: -0.5 * delta / (s * r),
                    }
                }
            }
            Self::Cauchy(delta) => {
                let d2 = delta * delta;
                let inv = 1.0 / (1.0 + s / d2);
                KernelValue {
                    rho: d2 * (1.0 + s / d2).ln(),
                    rho1: inv,
                    rho2: -inv * inv / d2,
                }
            }
            Self::Tukey(delta) => {
                let d2 = delta * delta;
                if s <= d2 {
                    let v = 1.0 - s / d2;
                    KernelValue {
                        rho: d2 / 3.0 * (1.0 - v * v * v),
                        rho1: v * v,
                        rho2: -2.0 * v / d2,
                    }
                } else {
                    KernelValue {
                        rho: d2 / 3.0,
                        rho1: 0.0,
                        rho2: 0.0,
                    }
                }
            }
            Self::GemanMcclure(delta) => {
                let d2 = delta * delta;
                let q = d2 / (d2 + s);
                KernelValue {
                    rho: s * q,
                    rho1: q * q,
                    rho2: -2.0 * q * q / (d2 + s),
                }
            }
        }
    }

    /// Applies Triggs' correction in place to a whitened residual `r` (length d) and row-major
    /// Jacobian `j` (d × cols). Returns ρ(s).
    pub fn correct(&self, r: &mut [f64], j: &mut [f64], cols: usize) -> f64 {
        let s: f64 = r.iter().map(|v| v * v).sum();
        let k = self.evaluate(s);
        let sqrt_rho1 = k.rho1.sqrt();
        let alpha = if s == 0.0 || k.rho2 <= 0.0 {
            0.0
        } else {
            1.0 - (1.0 + 2.0 * s * k.rho2 / k.rho1).max(0.0).sqrt()
        };
        let d = r.len();
        if alpha != 0.0 {
            // J ← (I − α r rᵀ / s) J: subtract α/s · r (rᵀ J).
            let factor = alpha / s;
            for c in 0..cols {
                let rtj: f64 = (0..d).map(|i| r[i] * j[i * cols + c]).sum();
                for i in 0..d {
                    j[i * cols + c] -= factor * r[i] * rtj;
                }
            }
        }
        for v in j.iter_mut() {
            *v *= sqrt_rho1;
        }
        let residual_scale = sqrt_rho1 / (1.0 - alpha);
        for v in r.iter_mut() {
            *v *= residual_scale;
        }
        k.rho
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn derivatives_match_numeric() {
        for kernel in [
            RobustKernel::Huber(1.3),
            RobustKernel::Cauchy(0.7),
            RobustKernel::Tukey(2.5),
            RobustKernel::GemanMcclure(0.8),
        ] {
            for &s in &[0.1, 0.5, 2.0, 10.0, 100.0] {
                let h = 1e-6 * s;
                let k = kernel.evaluate(s);
                let d1 = (kernel.evaluate(s + h).rho - kernel.evaluate(s - h).rho) / (2.0 * h);
                let d2 = (kernel.evaluate(s + h).rho1 - kernel.evaluate(s - h).rho1) / (2.0 * h);
                assert!((d1 - k.rho1).abs() < 1e-6, "{kernel:?} {s}");
                assert!((d2 - k.rho2).abs() < 1e-5, "{kernel:?} {s}");
            }
        }
    }

    #[test]
    fn parses_and_rejects() {
        assert_eq!(RobustKernel::parse("huber:2"), Ok(RobustKernel::Huber(2.0)));
        assert_eq!(RobustKernel::parse("Cauchy"), Ok(RobustKernel::Cauchy(1.0)));
        assert_eq!(
            RobustKernel::parse("tukey:4.685"),
            Ok(RobustKernel::Tukey(4.685))
        );
        assert_eq!(
            RobustKernel::parse("geman_mcclure:2"),
            Ok(RobustKernel::GemanMcclure(2.0))
        );
        assert!(RobustKernel::parse("welsch:1").is_err());
        assert!(RobustKernel::parse("huber:-1").is_err());
        assert!(RobustKernel::parse("huber:nan").is_err());
        assert!(RobustKernel::parse("tukey:1e300").is_err());
        assert!(RobustKernel::parse("cauchy:1e-300").is_err());
        assert!(RobustKernel::parse("cauchy:1e-9").is_ok());
        assert!(RobustKernel::parse("cauchy:1e9").is_ok());
    }
}
