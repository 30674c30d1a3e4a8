//! A session's latency budget as the wire shows it (`max_update_ms` at creation, see
//! docs/guide/latency.md): what statistics say about provisional answers and the corrections
//! that replace them.
//!
//! With a budget, an update the exact solve has not reflected in time (at most a quarter of the
//! budget) is answered *provisionally*: the recent part of the map is solved against the rest
//! as clients last saw it, and published. The exact solve keeps running off the request path; when it
//! lands, what it changed is published as a *correction*, whose size is reported here.

use serde::{Deserialize, Serialize};

/// The largest budget a session may ask for (a minute; a solve limit, not a latency, beyond).
pub const MAX_UPDATE_MS: u64 = 60_000;

/// Checks `max_update_ms` at session creation; `field` names it in the error.
pub fn check_budget(max_update_ms: u64) -> Result<(), String> {
    if (1..=MAX_UPDATE_MS).contains(&max_update_ms) {
        Ok(())
    } else {
        Err(format!(
            "max_update_ms must be between 1 and {MAX_UPDATE_MS} (milliseconds), got {max_update_ms}"
        ))
    }
}

/// A session's answers under its budget (`SessionStats.latency`).
#[derive(Clone, Debug, Serialize, Deserialize, utoipa::ToSchema)]
pub struct LatencyReport {
    pub max_update_ms: u64,
    /// The highest sequence the published estimate reflects, exactly or provisionally.
    pub answered_sequence: u64,
    /// The highest sequence the exact estimate reflects (`solved_sequence`): batches past it
    /// are answered provisionally until the exact solve reaches them.
    pub exact_sequence: u64,
    /// Updates answered provisionally so far (each answer covers every batch accepted until
    /// then).
    pub provisional_answers: u64,
    /// The last exact solve that landed after provisional answers.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub last_correction: Option<Correction>,
    /// Over the most recent corrections (at most [`CORRECTIONS_KEPT`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub corrections: Option<CorrectionStats>,
}

/// How many recent corrections [`CorrectionStats`] covers.
pub const CORRECTIONS_KEPT: usize = 16_384;

/// What an exact solve changed of the estimate clients had been given (provisional answers and
/// the exact values before them), over every variable with a position.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Correction {
    /// The sequence the landing exact estimate reflects.
    pub sequence: u64,
    /// Root mean square of the position changes over every positioned variable of the exact
    /// estimate (those it left alone count as 0), and the largest change, in map units.
    pub rmse: f64,
    pub max: f64,
    /// Variables whose position changed.
    pub moved: usize,
}

/// Quantiles of the recent corrections' `rmse` and `max`.
#[derive(Clone, Debug, Serialize, Deserialize, utoipa::ToSchema)]
pub struct CorrectionStats {
    pub count: u64,
    pub rmse_p50: f64,
    pub rmse_p99: f64,
    pub rmse_max: f64,
    pub max_p50: f64,
    pub max_p99: f64,
    pub max_max: f64,
}

impl CorrectionStats {
    /// Quantiles of `kept` (nearest rank); `None` when empty. `count`: every correction so far.
    pub fn of(kept: &[Correction], count: u64) -> Option<Self> {
        if kept.is_empty() {
            return None;
        }
        let sorted = |pick: fn(&Correction) -> f64| {
            let mut v: Vec<f64> = kept.iter().map(pick).collect();
            v.sort_by(f64::total_cmp);
            v
        };
        let quantile =
            |v: &[f64], q: f64| v[((v.len() as f64 * q).ceil() as usize).clamp(1, v.len()) - 1];
        let rmse = sorted(|c| c.rmse);
        let max = sorted(|c| c.max);
        Some(Self {
            count,
            rmse_p50: quantile(&rmse, 0.5),
            rmse_p99: quantile(&rmse, 0.99),
            rmse_max: quantile(&rmse, 1.0),
            max_p50: quantile(&max, 0.5),
            max_p99: quantile(&max, 0.99),
            max_max: quantile(&max, 1.0),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn budget_bounds_name_the_range() {
        assert!(check_budget(20).is_ok());
        assert!(check_budget(MAX_UPDATE_MS).is_ok());
        assert!(check_budget(0).unwrap_err().contains("between 1 and 60000"));
        assert!(check_budget(MAX_UPDATE_MS + 1).is_err());
    }

    #[test]
    fn quantiles_are_nearest_rank() {
        let kept: Vec<Correction> = (1..=100)
            .map(|i| Correction {
                sequence: i,
                rmse: i as f64,
                max: 2.0 * i as f64,
                moved: 1,
            })
            .collect();
        let s = CorrectionStats::of(&kept, 250).unwrap();
        assert_eq!(
            (s.count, s.rmse_p50, s.rmse_p99, s.rmse_max),
            (250, 50.0, 99.0, 100.0)
        );
        assert_eq!((s.max_p50, s.max_max), (100.0, 200.0));
        assert!(CorrectionStats::of(&[], 0).is_none());
    }
}
