//! Marginal covariances of a sliding window's keyframes: each state's 15 × 15 covariance (pose,
//! velocity, biases, in `nav_state`'s tangent order) given everything the window holds,
//! including the prior that summarises the marginalised keyframes.
//!
//! The window is small (at most a few dozen keyframes), so its information is factorised
//! afresh for each request, under the window's lock (which keyframe updates also take): the
//! answer is at the window's current estimate, and no keyframe can arrive meanwhile.

use std::time::Instant;

use super::engine::Window;
use super::Session;
use crate::api::wire::{Marginals, MarginalsQuery};
use crate::api::{ErrorKind, ServiceError};
use crate::problem::Key;
use crate::solver::marginals::{self, MarginalsError};

impl Session {
    pub(super) fn window_marginals(
        &self,
        window: &Window,
        query: &MarginalsQuery,
        start: Instant,
    ) -> Result<Marginals, ServiceError> {
        // Lock order: the window, then the state (as keyframe updates).
        let guard = window.window.lock().unwrap_or_else(|p| p.into_inner());
        let Some(w) = guard.as_ref() else {
            return Err(ServiceError::invalid(
                "not_started",
                "session",
                format!(
                    "session `{}` has no window yet: send its `start` message",
                    self.name
                ),
            ));
        };
        let problem = w.problem();
        // The problem also keeps marginalised keyframes, fixed: only the window's are asked.
        let in_window: Vec<Key> = w.window().iter().map(|(key, _, _)| *key).collect();
        check_in_window(&query.keys, &in_window)?;
        let factorized = marginals::Marginals::new(problem).map_err(|e| {
            ServiceError::new(ErrorKind::Invalid, "indeterminate_system", e.to_string())
        })?;
        let covariance = factorized.covariance(&query.keys).map_err(|e| match e {
            MarginalsError::UnknownVariable { key } | MarginalsError::Repeated { key } => {
                ServiceError::internal(format!("keyframe {key}: the factorisation disagrees"))
            }
        })?;
        let variables = query
            .keys
            .iter()
            .enumerate()
            .map(|(i, &key)| {
                super::inspect::marginal_of(
                    key,
                    problem.values.get(key).expect("checked above"),
                    &covariance.block(i, i),
                    factorized.gauge_fixed.binary_search(&key).is_ok(),
                )
            })
            .collect();
        let joint = query
            .joint
            .then(|| super::inspect::rows(&covariance.joint, covariance.dimension()));
        let st = self.lock();
        Ok(Marginals {
            session: self.name.clone(),
            sequence: st.mirror.sequence,
            solves: st.results.solves,
            variables,
            joint,
            // Fixed keys the window's own keyframes could be conditioned on (none: the marginalised
            // ones it keeps fixed are summarised by its prior).
            gauge_fixed: factorized
                .gauge_fixed
                .iter()
                .copied()
                .filter(|k| in_window.contains(k))
                .collect(),
            reused_factorization: false,
            factorize_seconds: factorized.factorize_seconds,
            seconds: start.elapsed().as_secs_f64(),
        })
    }
}

/// Every key a query names is a keyframe in the window, named once.
fn check_in_window(keys: &[Key], in_window: &[Key]) -> Result<(), ServiceError> {
    for (i, key) in keys.iter().enumerate() {
        if !in_window.contains(key) {
            return Err(ServiceError::invalid(
                "unknown_variable",
                format!("keys[{i}]"),
                format!("keyframe {key} is not in the window (marginalised, or never created)"),
            ));
        }
        if keys[..i].contains(key) {
            return Err(ServiceError::bad_request(
                "invalid_value",
                format!("keys[{i}]"),
                format!("variable {key} is named twice"),
            ));
        }
    }
    Ok(())
}
