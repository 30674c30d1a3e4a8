//! Accepting a batch, in four steps: validate (limits, the batch against the mirror), journal
//! (durable sessions), mirror (what clients read and later batches validate against), schedule
//! (apply it to the problem now, or queue it behind a running solve, and maybe start a solve).
//! A client's batch is acknowledged once durable ([`Session::apply_batch`]); a batch replayed
//! from the journal or a snapshot skips the client's limits, the journal and the
//! acknowledgement ([`Session::replay_batch`]).

use std::collections::HashSet;
use std::sync::{Arc, MutexGuard};

use super::batch::{self, AdmissionDeadline, PreparedBatch, SessionView};
use super::durable::Durable;
use super::engine::{self, Engine};
use super::producers::{self, Admission, Origin};
use super::robots;
use super::{Session, State};
use crate::api::wire::{Batch, BatchAck, Estimate, FactorId, SessionEvent, VariableValue};
use crate::api::ServiceError;
use crate::journal::KeptAck;
use crate::problem::Key;
use crate::solver;

impl Session {
    /// Validates and accepts a batch, journals it (durable sessions) and only then acknowledges
    /// it; returns the acknowledgement and whether a solve reflecting it is scheduled (so a
    /// caller may wait for it).
    pub fn apply_batch(self: &Arc<Self>, batch: Batch) -> Result<(BatchAck, bool), ServiceError> {
        let (origin, mut st) = self.lock_for_batch(&batch)?;
        if let Some(origin) = &origin {
            if let Admission::Repeat(kept) =
                st.producers
                    .admit(&self.name, origin, self.limits.max_producers_per_session)?
            {
                return Ok(self.repeat(&st, origin, &kept));
            }
        }
        self.check_batch_size(&batch)?;
        self.check_session_memory(&st, &batch)?;
        let mut durable = self.durable.lock().unwrap_or_else(|p| p.into_inner());
        // Taken with the journal held, before the batch is written or a solve of it scheduled:
        // a solve's `journal_barrier` then waits for this batch's acknowledgement.
        let acknowledging = self.acknowledging.read().unwrap_or_else(|p| p.into_inner());
        let wire_copy = durable.is_some().then(|| batch.clone());
        // Step 1, validate.
        let deadline = AdmissionDeadline::after(self.limits.max_admission_ms);
        let mut prepared = self.validate(&st, batch, Some(deadline))?;
        self.check_session_size(&st, &prepared)?;
        let sequence = self.next_sequence(&st)?;
        // Step 2, journal (not yet durable: the fsync below runs with the session unlocked).
        let wire_copy = match (durable.as_mut(), wire_copy) {
            (Some(d), Some(copy)) => {
                Some(d.write_batch(&self.name, sequence, copy, &prepared, st.robots.as_ref())?)
            }
            _ => None,
        };
        let mirrored = self.mirror_batch(
            &mut st,
            durable.as_mut(),
            wire_copy,
            sequence,
            &mut prepared,
            None,
            None,
        );
        let ack = self.schedule_batch(&mut st, sequence, prepared, &mirrored, origin.as_ref());
        let will_solve = st.results.solved_sequence < sequence && st.schedule.phase.solve_coming();
        if let Some(d) = durable.as_mut() {
            d.maybe_snapshot(self, &st);
        }
        // With a latency budget: when to answer provisionally (see `Latency::wait`).
        let provisional_after = st
            .latency
            .as_ref()
            .map(|l| l.wait(st.model.problem.is_none()));
        // The fsync runs with the session and its journal unlocked, so the solve just scheduled
        // (and reads) run meanwhile, and the session's next batches are written and share it
        // (group commit, `journal::group_commit`); the acknowledgement below, and everything a
        // solve publishes (it passes `journal_barrier` first), wait for the batch to be durable.
        drop(st);
        // Counted from here, the wait overlaps the fsync (as the exact solve does); the answer
        // is published only once the batch is durable (`journal_barrier`).
        if let Some(after) = provisional_after {
            self.spawn_provisional_answer(sequence, after, false);
        }
        let pending = durable.as_ref().map(|d| d.pending());
        drop(durable);
        if let Some(e) = mirrored.journal_error {
            // The batch is journalled but a merge it completed is not: the session's state is
            // ahead of its files, so it stops here (see `journal_sync_failed`).
            drop(acknowledging);
            return Err(self.sync_refused(e));
        }
        if let Err(e) = pending.map_or(Ok(()), |p| p.wait(&self.name)) {
            // Nothing is acknowledged; the step-down below takes the session's locks.
            drop(acknowledging);
            return Err(self.sync_refused(e));
        }
        self.publish_accepted(sequence);
        self.emit(SessionEvent::Ack(ack.clone()));
        if !mirrored.new_values.is_empty() {
            self.emit(SessionEvent::Estimate(Estimate {
                session: self.name.clone(),
                sequence,
                variables: mirrored.new_values,
            }));
        }
        for merge in mirrored.merges {
            self.emit(SessionEvent::Merge {
                session: self.name.clone(),
                merge,
            });
        }
        Ok((ack, will_solve))
    }

    /// Applies a batch the journal (or a snapshot) holds, in recovery or adoption: it is the
    /// truth the session is rebuilt from, so neither a client's limits nor a producer's repeat
    /// check apply, and nothing is journalled or acknowledged again: acknowledging it again
    /// would tell subscribers something new was applied, with a producer's `accepted_through`
    /// going backwards. The recovery's solve publishes the estimate.
    /// `ids`: the factor ids to give the batch's factors (a snapshot's), else the next ones.
    /// `placed`: its robots' values are in the map frame already (a snapshot's estimate), not
    /// in their odometry frames (a journalled batch, as the robots sent it).
    pub(super) fn replay_batch(
        self: &Arc<Self>,
        batch: Batch,
        ids: Option<Vec<FactorId>>,
        placed: bool,
    ) -> Result<(), ServiceError> {
        let (origin, mut st) = self.lock_for_batch(&batch)?;
        let mut durable = self.durable.lock().unwrap_or_else(|p| p.into_inner());
        // Kept for the next snapshot's base, as a journalled batch is.
        let wire_copy = durable.is_some().then(|| batch.clone());
        let mut prepared = self.validate(&st, batch, None)?;
        let sequence = self.next_sequence(&st)?;
        let mirrored = self.mirror_batch(
            &mut st,
            durable.as_mut(),
            wire_copy,
            sequence,
            &mut prepared,
            ids,
            Some(if placed {
                Placed::InMap
            } else {
                Placed::InOdometry
            }),
        );
        self.schedule_batch(&mut st, sequence, prepared, &mirrored, origin.as_ref());
        drop(st);
        drop(durable);
        self.publish_accepted(sequence);
        Ok(())
    }

    /// Step 1, validate: the batch against the mirror (and the factor types), into typed parts
    /// that cannot fail to apply; refused when too many factors already wait for the running
    /// solve. `deadline`: how long a client's batch may take (none for a replay).
    fn validate(
        &self,
        st: &State,
        batch: Batch,
        deadline: Option<AdmissionDeadline>,
    ) -> Result<PreparedBatch, ServiceError> {
        let factor_types = self.factor_types();
        let prepared = batch::prepare(
            batch,
            &SessionView {
                kind: self.kind,
                mirror: &st.mirror.entries,
                live_factors: &st.mirror.live_factors,
                factor_types: &factor_types,
                outliers: st.outliers.policy,
                deadline,
            },
        )?;
        let queued = st.schedule.queued_factors();
        if st.model.problem.is_none()
            && queued + prepared.factor_count() > self.limits.max_pending_factors
        {
            return Err(ServiceError::too_many(
                format!(
                    "session `{}` has {} factors waiting for the running solve; {} more would exceed the limit of {}",
                    self.name,
                    queued,
                    prepared.factor_count(),
                    self.limits.max_pending_factors
                ),
                1,
            ));
        }
        Ok(prepared)
    }

    fn next_sequence(&self, st: &State) -> Result<u64, ServiceError> {
        st.mirror
            .sequence
            .checked_add(1)
            .ok_or_else(|| self.sequences_exhausted())
    }

    /// Step 3, mirror: gives the validated (and journalled) batch its sequence and factor ids
    /// and updates the mirror, first: later batches validate against it even while this one
    /// waits for the problem. `wire_copy`: the batch as the journal holds it, kept for the
    /// next snapshot of a durable session. A session's robots route the batch here (see
    /// `session::robots`): its robots' values move into their frames (unless `placed`, or a
    /// replay), held closures leave `prepared`, and the merges it completes are decided and
    /// journalled (not in a replay: the journal's merge records follow its batch).
    #[allow(clippy::too_many_arguments)]
    fn mirror_batch(
        &self,
        st: &mut State,
        mut durable: Option<&mut Durable>,
        wire_copy: Option<Batch>,
        sequence: u64,
        prepared: &mut PreparedBatch,
        ids: Option<Vec<FactorId>>,
        replay: Option<Placed>,
    ) -> Mirrored {
        let placed = replay == Some(Placed::InMap);
        st.mirror.sequence = sequence;
        let factor_ids = st.mirror.assign_factor_ids(ids, prepared.factors.len());
        if let Some(robots) = st.robots.as_ref().filter(|_| !placed) {
            robots.place_new_values(prepared);
        }
        if let (Some(d), Some(copy)) = (durable.as_deref_mut(), wire_copy) {
            // A bundle adjustment's restarts start from the values given (`bundle`).
            let keeps_given = !self.kind.eliminate.is_empty();
            d.track(copy.factors, &factor_ids, prepared, keeps_given);
        }
        let new_values = st.mirror.accept(prepared, &factor_ids, sequence);
        let mut mirrored = Mirrored {
            active_ids: factor_ids.clone(),
            factor_ids,
            new_values,
            merges: Vec::new(),
            journal_error: None,
        };
        if let Some(robots) = st.robots.as_mut() {
            robots.remove_factors(&prepared.remove);
            let plan = robots.route(
                prepared,
                &mirrored.factor_ids,
                &mut st.mirror.entries,
                sequence,
                replay.is_some(),
            );
            mirrored.active_ids = plan.active_ids;
            prepared.merges = plan.merges;
            if !plan.moved_values.is_empty() {
                // The batch's own values a merge moved are carried once, where they ended.
                let moved: HashSet<Key> = plan.moved_values.iter().map(|v| v.key).collect();
                mirrored.new_values.retain(|v| !moved.contains(&v.key));
                mirrored.new_values.extend(plan.moved_values);
            }
            for (record, report) in plan.records {
                if let Some(d) = durable.as_deref_mut() {
                    if let Err(e) = d.write_merge(&self.name, sequence, record) {
                        mirrored.journal_error.get_or_insert(e);
                    }
                }
                mirrored.merges.extend(report);
            }
        }
        st.outliers.remove_factors(&prepared.remove);
        st.outliers.route(prepared, &mut mirrored.active_ids);
        mirrored
    }

    /// Step 4, schedule: applies the batch to the problem (or queues it behind the running
    /// solve), records the producer's progress, maybe starts a solve, and returns the
    /// acknowledgement.
    fn schedule_batch(
        self: &Arc<Self>,
        st: &mut State,
        sequence: u64,
        prepared: PreparedBatch,
        mirrored: &Mirrored,
        origin: Option<&Origin>,
    ) -> BatchAck {
        if let Some(latency) = st.latency.as_mut() {
            latency.take_in(sequence, &prepared);
        }
        let predicted = prepared.predicted.clone();
        // Only the factors that enter the problem (a session's robots hold some back).
        let active = mirrored.active_ids.clone();
        if st.model.problem.is_some() {
            self.apply_prepared(st, sequence, prepared, active);
        } else {
            st.schedule.queue_batch(sequence, prepared, active);
        }
        let mut ack = BatchAck {
            session: self.name.clone(),
            sequence,
            factor_ids: mirrored.factor_ids.clone(),
            predicted,
            reflected: st.results.solved_sequence >= sequence,
            producer: None,
            producer_seq: None,
            accepted_through: None,
            duplicate: false,
        };
        if let Some(origin) = origin {
            st.producers.record(origin, &ack);
            ack.producer = Some(origin.producer.clone());
            ack.producer_seq = Some(origin.seq);
            ack.accepted_through = Some(st.producers.accepted_through(&origin.producer));
        }
        self.maybe_schedule(st);
        ack
    }

    /// Tells requests waiting for `sequence` (`after`) that it is accepted.
    fn publish_accepted(&self, sequence: u64) {
        // Batches sharing an fsync may get here in any order.
        self.accepted.send_if_modified(|accepted| {
            std::mem::replace(accepted, sequence.max(*accepted)) < sequence
        });
    }

    /// The answer to a repeat of `origin`'s batch: its original acknowledgement (published again,
    /// so a zenoh producer that lost it hears it), nothing applied.
    fn repeat(&self, st: &State, origin: &Origin, kept: &KeptAck) -> (BatchAck, bool) {
        // The original may still be on its way to the disk.
        self.journal_barrier();
        let mut ack = producers::original_ack(
            kept,
            &self.name,
            &origin.producer,
            st.results.solved_sequence,
        );
        ack.accepted_through = Some(st.producers.accepted_through(&origin.producer));
        self.emit(SessionEvent::Ack(ack.clone()));
        let will_solve =
            st.results.solved_sequence < ack.sequence && st.schedule.phase.solve_coming();
        (ack, will_solve)
    }

    /// Step 4 with the problem here: applies a validated batch to it and decides whether it
    /// needs a solve.
    pub(super) fn apply_prepared(
        &self,
        st: &mut State,
        sequence: u64,
        prepared: PreparedBatch,
        factor_ids: Vec<FactorId>,
    ) {
        let change = add_to_problem(st, prepared, factor_ids);
        st.schedule.factors_since_solve += change.added_factors;
        st.schedule.structural |= change.structural;
        // A batch that only adds factors whose total chi2 at the current (converged) estimate is
        // below the function tolerance of the whole cannot make a solve gain more than that
        // tolerance: the estimate stays the optimum to within what a solve would reach. This is
        // what makes appending an odometry-predicted pose free.
        if !change.adds_variables
            && change.added_factors == 0
            && !change.structural
            && !st.schedule.phase.is_dirty()
        {
            // An empty batch: whatever reflected the last one reflects this one (a `wait` on it
            // must not wait for a timer, or for ever under `manual`).
            st.results.reflected(sequence);
            self.solved.send_replace(sequence);
            return;
        }
        let new_chi2 = change.new_chi2;
        let total = st.results.chi2.unwrap_or(0.0) + new_chi2;
        let negligible = new_chi2 <= st.options.function_tolerance * total || new_chi2 == 0.0;
        let was_converged =
            st.results.converged && !st.schedule.phase.is_dirty() && st.results.chi2.is_some();
        st.results.chi2 = st.results.chi2.map(|_| total);
        if was_converged && !change.structural && negligible {
            st.schedule.seeds.clear();
            st.results.skipped(sequence);
            self.solved.send_replace(sequence);
        } else {
            st.schedule.phase.mark_dirty();
            st.results.converged = false;
        }
    }
}

/// Where a replayed batch's robot values are: a journalled batch's as the robots sent them, a
/// snapshot's in the map frame already.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Placed {
    InOdometry,
    InMap,
}

/// What the mirror step did with an accepted batch.
struct Mirrored {
    /// Ids of all its factors, in order, and of those that enter the problem now.
    factor_ids: Vec<FactorId>,
    active_ids: Vec<FactorId>,
    /// The values it set (for the `estimate` event).
    new_values: Vec<VariableValue>,
    /// The merges it completed (for `merge` events).
    merges: Vec<crate::api::robots::MergeReport>,
    /// A merge record the journal could not take.
    journal_error: Option<ServiceError>,
}

/// What applying a batch to the problem changed.
struct ProblemChange {
    added_factors: usize,
    adds_variables: bool,
    /// Removals, fixes or guesses: the next solve is of the whole problem.
    structural: bool,
    /// What the new factors add to chi2 at the current estimate.
    new_chi2: f64,
}

/// Adds a validated batch's variables and factors to the problem (present in `st`), removes,
/// fixes and guesses what it says, and seeds the next solve with what the new factors touch.
fn add_to_problem(
    st: &mut State,
    prepared: PreparedBatch,
    factor_ids: Vec<FactorId>,
) -> ProblemChange {
    let super::state::Model {
        problem,
        index,
        factor_ids: ids,
        ..
    } = &mut st.model;
    let seeds = &mut st.schedule.seeds;
    let problem = problem.as_mut().expect("caller checked");
    let index = index.as_mut().expect("kept with the problem");
    let first_new_factor = problem.factors().len();
    let structural = prepared.changes_more_than_it_adds();
    let adds_variables = !prepared.variables.is_empty();
    for v in prepared.variables {
        let at = problem.add_variable(v.key, v.value).expect("validated");
        index.given.record(problem, at);
        if v.fixed {
            problem.set_fixed(v.key, true).expect("validated");
        }
    }
    let added_factors = prepared.factors.len();
    for (f, id) in prepared.factors.into_iter().zip(factor_ids) {
        // No label: `prepare` checked what the problem's errors would name, and a session's
        // factor is named by its id.
        problem
            .add_checked_factor_sqrt(f.factor, f.sqrt_information, f.robust, String::new())
            .expect("validated");
        ids.push(id);
    }
    let moved = robots::apply_to_problem(problem, ids, prepared.merges);
    // chi2 the new factors add at the current estimate, before removals shift indices.
    let new_chi2 = solver::evaluate_chi2(&problem.factors()[first_new_factor..], &problem.values)
        .unwrap_or(f64::INFINITY);
    index.extend(problem, first_new_factor);
    for f in &problem.factors()[first_new_factor..] {
        seeds.extend_from_slice(f.variables());
    }
    if !prepared.remove.is_empty() {
        let remove: HashSet<FactorId> = prepared.remove.into_iter().collect();
        let keep: Vec<bool> = ids.iter().map(|id| !remove.contains(id)).collect();
        problem.retain_factors(|i| keep[i]);
        ids.retain(|id| !remove.contains(id));
        index.rebuild(problem);
    }
    for (key, fixed) in prepared.fix {
        problem.set_fixed(key, fixed).expect("validated");
    }
    for (key, v) in &prepared.guesses {
        let idx = problem.values.index_of(*key).expect("validated");
        problem.values.set(idx, v.as_ref());
        index.given.record(problem, idx);
    }
    robots::resync_mirror(problem, &mut st.mirror.entries, &moved);
    ProblemChange {
        added_factors,
        adds_variables,
        structural,
        new_chi2,
    }
}

impl Session {
    /// The batch's producer fields and the session's state, locked: refused for a session
    /// that takes no batches (a sliding window) or that is deleted.
    fn lock_for_batch(
        &self,
        batch: &Batch,
    ) -> Result<(Option<Origin>, MutexGuard<'_, State>), ServiceError> {
        let Engine::Graph(_) = &self.engine else {
            return Err(engine::batches_refused(&self.name));
        };
        let origin = Origin::of(batch)?;
        let st = self.lock();
        if st.schedule.phase.is_deleted() {
            return Err(self.gone());
        }
        Ok((origin, st))
    }
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    use super::*;

    /// Issue 52, item 10: at sequence `u64::MAX` the next batch is refused and the session made
    /// read-only; it is never acknowledged with sequence 0.
    #[test]
    fn the_batch_after_the_last_sequence_is_refused_not_wrapped() {
        let (_runtime, pool, session) = crate::session::test_session("last");
        session.lock().mirror.sequence = u64::MAX - 1;
        let pose = |key: u64| -> Batch {
            serde_json::from_value(json!({"variables": [{"key": key, "kind": "se2",
                "value": [0, 0, 0], "fixed": true}]}))
            .unwrap()
        };
        let (ack, _) = session.apply_batch(pose(0)).unwrap();
        assert_eq!(ack.sequence, u64::MAX);
        let refused = session.apply_batch(pose(1)).unwrap_err();
        assert_eq!(refused.body.code, "session_corrupt", "{refused:?}");
        assert!(refused.body.message.contains("read-only"), "{refused:?}");
        assert_eq!(session.lock().mirror.sequence, u64::MAX);
        assert!(
            !session.lock().mirror.entries.contains_key(&1),
            "nothing applied"
        );
        assert!(session.corruption().is_some());
        drop(session);
        pool.shutdown(std::time::Duration::from_secs(5));
    }

    /// Issue 52, item 14: once another instance has claimed the session's next ownership epoch
    /// (it took the session over while this one was stopped), a batch is applied and written
    /// here but never acknowledged, the session steps down, and the new owner's files hold
    /// only what was acknowledged before.
    #[test]
    fn a_write_after_a_takeover_elsewhere_is_not_acknowledged() {
        use crate::journal::{JournalConfig, SessionDir};
        let (_runtime, pool, session) = crate::session::test_session("fenced");
        let state = std::env::temp_dir().join(format!("factord-fenced-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&state);
        let request = serde_json::from_value(json!({"session": "fenced",
            "kind": "pose_graph_2d"}))
        .unwrap();
        let mut dir = SessionDir::create(&state, "fenced", &request, None).unwrap();
        dir.claim_first("a").unwrap();
        let config = JournalConfig::default();
        let journal = dir.open_journal(config.fsync).unwrap();
        session.attach(crate::session::Durability {
            dir: dir.clone(),
            journal,
            config,
        });
        let pose = |key: u64| -> Batch {
            serde_json::from_value(json!({"variables": [{"key": key, "kind": "se2",
                "value": [0, 0, 0], "fixed": true}]}))
            .unwrap()
        };
        assert_eq!(session.apply_batch(pose(0)).unwrap().0.sequence, 1);
        let taken = dir.take_over("b").unwrap();
        let refused = session.apply_batch(pose(1)).unwrap_err();
        assert_eq!(refused.body.code, "ownership_lost", "{refused:?}");
        assert_eq!(refused.body.retry_after, Some(1));
        let after = session.apply_batch(pose(2)).unwrap_err();
        assert_eq!(after.body.code, "session_moving", "{after:?}");
        assert!(session.ownership_superseded());
        let kept = taken.load_state().unwrap();
        assert_eq!(kept.entries.len(), 1, "only the acknowledged batch");
        drop(session);
        pool.shutdown(std::time::Duration::from_secs(5));
        std::fs::remove_dir_all(&state).unwrap();
    }
}
