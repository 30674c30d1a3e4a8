//! Possibly wrong loop closures in a streaming session: held out of the problem until the
//! service decides they fit, and decided again as the map grows.
//!
//! A *candidate* (a factor marked `"outlier": "auto"`, or a loop closure of a session whose
//! policy is `auto`, see [`crate::api::outliers`]) is accepted, acknowledged and journalled like
//! any factor, but held here instead of entering the problem. Two deciders (`decide`):
//!
//! - **The gate**, on every streamed solve: once the incremental engine has taken the batch's
//!   other factors in, each pending candidate is weighed alone against the estimate by the
//!   innovation's Mahalanobis distance (`IncrementalEngine::innovation`: the rise of the
//!   least-squares cost it would cause, in its noise and the estimate's uncertainty). Within the
//!   χ² quantile at 1 − 10⁻⁶ it enters the problem, and a second engine update takes it in;
//!   beyond, it is *rejected* and stays held. A correct closure after a long excursion passes
//!   (the estimate's uncertainty has grown with the drift it corrects), which a gate on the
//!   closure's error at the estimate alone cannot tell from a wrong one.
//! - **Consolidation**, on every full solve (the first, after a removal, after a recovery) and
//!   once the session rests after gate decisions: graduated non-convexity over the whole
//!   problem with every candidate, accepted and held (`solver::optimize_gnc`): the batch
//!   answer, exact on the benchmarks up to 50 % wrong closures, which also corrects what the
//!   gate decided alone (a wrong closure that arrived before the map could tell, a right one
//!   rejected before the closures that vindicate it).
//!
//! Decisions are not journalled: they are derived from the candidates, which are. A recovery
//! routes the journalled candidates here again, and its first solve consolidates.

mod decide;
mod session;

use std::collections::{BTreeMap, BTreeSet};

pub(crate) use decide::{consolidate, gate, noise_scale, GATE_CONFIDENCE};

use super::prepared::{PreparedBatch, PreparedFactor};
use crate::api::outliers::{CandidateReport, OutlierDecisions, OutlierPolicy, OutliersReport};
use crate::api::wire::FactorId;
use crate::problem::Key;

/// Who decided a candidate.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum DecidedBy {
    Gate,
    GraduatedNonConvexity,
}

impl DecidedBy {
    fn wire(self) -> &'static str {
        match self {
            DecidedBy::Gate => "gate",
            DecidedBy::GraduatedNonConvexity => "graduated_non_convexity",
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Status {
    Pending,
    Accepted,
    Rejected,
}

#[derive(Clone, Debug)]
struct Candidate {
    keys: Vec<Key>,
    status: Status,
    distance: Option<f64>,
    decided_by: Option<DecidedBy>,
}

/// One decision a solve took.
#[derive(Clone, Debug)]
pub(crate) struct Decision {
    pub id: FactorId,
    pub accepted: bool,
    pub distance: Option<f64>,
    pub by: DecidedBy,
}

/// The session's candidates.
#[derive(Default)]
pub(crate) struct Outliers {
    pub(crate) policy: OutlierPolicy,
    candidates: BTreeMap<FactorId, Candidate>,
    /// The factors of held candidates (pending and rejected), out of the problem; a solve takes
    /// those it decides ([`Outliers::take_for_solve`]) and gives back what stays held.
    held: BTreeMap<FactorId, PreparedFactor>,
    consolidations: u64,
    /// The gate decided since the last consolidation: consolidate when the session rests.
    gate_decisions: u64,
    /// The session rested after gate decisions: the next solve consolidates.
    pub(crate) requested: bool,
}

/// What a solve takes to decide.
pub(crate) struct OutlierWork {
    /// Consolidate (a full solve): every held candidate, and the accepted ones' ids.
    pub consolidate: bool,
    pub held: Vec<(FactorId, PreparedFactor)>,
    pub accepted: BTreeSet<FactorId>,
}

/// What a solve decided, and what stays held.
#[derive(Default)]
pub(crate) struct OutlierOutcome {
    pub decisions: Vec<Decision>,
    pub held: Vec<(FactorId, PreparedFactor)>,
}

impl Outliers {
    pub(crate) fn new(policy: OutlierPolicy) -> Self {
        Self {
            policy,
            ..Self::default()
        }
    }

    /// No candidate ever arrived (or all were removed).
    pub(crate) fn is_empty(&self) -> bool {
        self.candidates.is_empty()
    }

    /// Moves the batch's candidates out of `prepared` (their ids out of `active`, which lists
    /// the ids of `prepared.factors`) into the held set.
    pub(crate) fn route(&mut self, prepared: &mut PreparedBatch, active: &mut Vec<FactorId>) {
        if !prepared.factors.iter().any(|f| f.candidate) {
            return;
        }
        let factors = std::mem::take(&mut prepared.factors);
        let ids = std::mem::take(active);
        for (f, id) in factors.into_iter().zip(ids) {
            if f.candidate {
                self.candidates.insert(
                    id,
                    Candidate {
                        keys: f.factor.keys().to_vec(),
                        status: Status::Pending,
                        distance: None,
                        decided_by: None,
                    },
                );
                self.held.insert(id, f);
            } else {
                prepared.factors.push(f);
                active.push(id);
            }
        }
    }

    /// Forgets candidates the client removed (an accepted one leaves the problem as any factor).
    pub(crate) fn remove_factors(&mut self, ids: &[FactorId]) {
        for id in ids {
            self.candidates.remove(id);
            self.held.remove(id);
        }
    }

    /// Whether the next solve should consolidate though it streams (the session rested after
    /// gate decisions).
    pub(crate) fn consolidation_due(&self) -> bool {
        self.gate_decisions > 0
    }

    /// The candidates a solve decides: all of them when it consolidates, else the pending ones.
    pub(crate) fn take_for_solve(&mut self, consolidate: bool) -> OutlierWork {
        let candidates = &self.candidates;
        let held = if consolidate {
            std::mem::take(&mut self.held).into_iter().collect()
        } else {
            let pending: Vec<FactorId> = self
                .held
                .keys()
                .copied()
                .filter(|id| candidates.get(id).map(|c| c.status) == Some(Status::Pending))
                .collect();
            pending
                .into_iter()
                .filter_map(|id| self.held.remove(&id).map(|f| (id, f)))
                .collect()
        };
        let accepted = if consolidate {
            candidates
                .iter()
                .filter(|(_, c)| c.status == Status::Accepted)
                .map(|(&id, _)| id)
                .collect()
        } else {
            BTreeSet::new()
        };
        OutlierWork {
            consolidate,
            held,
            accepted,
        }
    }

    /// Takes back the candidates of a solve that decided nothing (it failed first).
    pub(crate) fn give_back(&mut self, work: OutlierWork) {
        self.hold_again(work.held);
    }

    /// Holds `held` again, but for candidates the client removed while a solve had them.
    fn hold_again(&mut self, held: Vec<(FactorId, PreparedFactor)>) {
        for (id, f) in held {
            if self.candidates.contains_key(&id) {
                self.held.insert(id, f);
            }
        }
    }

    /// Takes back what a solve decided; the event to publish when it decided anything that
    /// changed a candidate's standing. `sequence`: the sequence the solve reflected.
    pub(crate) fn finish(
        &mut self,
        outcome: OutlierOutcome,
        consolidated: bool,
        sequence: u64,
    ) -> Option<OutlierDecisions> {
        self.hold_again(outcome.held);
        if consolidated {
            self.consolidations += 1;
            self.gate_decisions = 0;
        }
        let mut event = OutlierDecisions {
            sequence,
            decided_by: String::new(),
            accepted: Vec::new(),
            rejected: Vec::new(),
        };
        for d in outcome.decisions {
            let Some(c) = self.candidates.get_mut(&d.id) else {
                continue;
            };
            let status = if d.accepted {
                Status::Accepted
            } else {
                Status::Rejected
            };
            if d.by == DecidedBy::Gate {
                self.gate_decisions += 1;
            }
            let changed = c.status != status;
            c.status = status;
            c.distance = d.distance;
            c.decided_by = Some(d.by);
            event.decided_by = d.by.wire().to_string();
            if changed {
                let report = report_of(d.id, c);
                if d.accepted {
                    event.accepted.push(report);
                } else {
                    event.rejected.push(report);
                }
            }
        }
        (!event.accepted.is_empty() || !event.rejected.is_empty()).then_some(event)
    }

    /// Each held candidate's χ² contribution `‖R e‖²` at `values` (what it would add were it
    /// in), for drawing it: the web view and ROS 2 markers colour a rejected closure by it.
    pub(crate) fn held_chi2(&self, values: &crate::problem::Values) -> Vec<(FactorId, f64)> {
        self.held
            .iter()
            .filter_map(|(&id, f)| {
                let vars: Option<Vec<&dyn crate::problem::Variable>> =
                    f.factor.keys().iter().map(|&k| values.get(k)).collect();
                let mut error = vec![0.0; f.factor.residual_dim()];
                f.factor.evaluate(&vars?, &mut error, None).ok()?;
                let mut whitened = vec![0.0; error.len()];
                f.sqrt_information.whiten_vector(&error, &mut whitened);
                Some((id, whitened.iter().map(|v| v * v).sum()))
            })
            .collect()
    }

    /// What `GET /v1/sessions/{s}/outliers` shows.
    pub(crate) fn report(&self, session: &str) -> OutliersReport {
        let listed = |status: Status| -> Vec<CandidateReport> {
            self.candidates
                .iter()
                .filter(|(_, c)| c.status == status)
                .map(|(&id, c)| report_of(id, c))
                .collect()
        };
        OutliersReport {
            session: session.to_string(),
            policy: self.policy,
            accepted: self
                .candidates
                .values()
                .filter(|c| c.status == Status::Accepted)
                .count() as u64,
            pending: listed(Status::Pending),
            rejected: listed(Status::Rejected),
            consolidations: self.consolidations,
            gate_confidence: GATE_CONFIDENCE,
        }
    }
}

fn report_of(id: FactorId, c: &Candidate) -> CandidateReport {
    CandidateReport {
        factor_id: id,
        keys: c.keys.clone(),
        distance: c.distance,
        decided_by: c.decided_by.map(|d| d.wire().to_string()),
    }
}
