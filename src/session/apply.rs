//! Accepting a batch: size limits, validation against the mirror, journalling, updating the
//! mirror, and applying it to the problem now or queueing it behind a running solve.

use std::collections::HashSet;
use std::sync::Arc;

use super::batch::{self, AdmissionDeadline, PreparedBatch, SessionView};
use super::engine::{self, Engine};
use super::mirror::{heap_values, value_of, WireValue};
use super::producers::{self, Admission, Origin};
use super::{inspect, MirrorEntry, Session, State};
use crate::api::catalogue;
use crate::api::wire::{Batch, BatchAck, Estimate, FactorId, SessionEvent};
use crate::api::ErrorKind;
use crate::api::ServiceError;
use crate::journal::KeptAck;
use crate::solver;

impl Session {
    /// Validates and accepts a batch, journals it (durable sessions) and only then acknowledges
    /// it; returns the acknowledgement and whether a solve reflecting it is scheduled (so a
    /// caller may wait for it).
    pub fn apply_batch(self: &Arc<Self>, batch: Batch) -> Result<(BatchAck, bool), ServiceError> {
        self.accept_batch(batch, None, true)
    }

    /// `ids`: the factor ids to give the batch's factors (a snapshot's), else the next ones.
    /// `journal`: append it to the journal (not when it is being replayed from there).
    pub(super) fn accept_batch(
        self: &Arc<Self>,
        batch: Batch,
        ids: Option<Vec<FactorId>>,
        journal: bool,
    ) -> Result<(BatchAck, bool), ServiceError> {
        let Engine::Graph(_) = &self.engine else {
            return Err(engine::batches_refused(&self.name));
        };
        let origin = Origin::of(&batch)?;
        let mut st = self.lock();
        if st.deleted {
            return Err(self.gone());
        }
        // A replay applies what the journal holds: it is the truth the table is rebuilt from.
        if let (Some(origin), true) = (&origin, journal) {
            if let Admission::Repeat(kept) =
                st.producers
                    .admit(&self.name, origin, self.limits.max_producers_per_session)?
            {
                return Ok(self.repeat(&st, origin, &kept));
            }
        }
        // Limits hold for what clients send; a journal replay restores what was accepted.
        if journal {
            self.check_batch_size(&batch)?;
        }
        let mut durable = self.durable.lock().unwrap_or_else(|p| p.into_inner());
        // Taken with the journal held, before the batch is written or a solve of it scheduled:
        // a solve's `journal_barrier` then waits for this batch's acknowledgement.
        let acknowledging =
            journal.then(|| self.acknowledging.read().unwrap_or_else(|p| p.into_inner()));
        let wire_copy = durable.is_some().then(|| batch.clone());
        let factor_types = self.factor_types();
        let prepared = batch::prepare(
            batch,
            &SessionView {
                kind: self.kind,
                mirror: &st.mirror,
                live_factors: &st.live_factors,
                factor_types: &factor_types,
                deadline: journal.then(|| AdmissionDeadline::after(self.limits.max_admission_ms)),
            },
        )?;
        if st.problem.is_none()
            && st.pending_factors + prepared.factor_count() > self.limits.max_pending_factors
        {
            return Err(ServiceError::too_many(
                format!(
                    "session `{}` has {} factors waiting for the running solve; {} more would exceed the limit of {}",
                    self.name,
                    st.pending_factors,
                    prepared.factor_count(),
                    self.limits.max_pending_factors
                ),
                1,
            ));
        }
        if journal {
            self.check_session_size(&st, &prepared)?;
        }
        let Some(sequence) = st.sequence.checked_add(1) else {
            return Err(self.sequences_exhausted());
        };
        let wire_copy = match (durable.as_mut(), wire_copy, journal) {
            (Some(d), Some(copy), true) => {
                Some(d.write_batch(&self.name, sequence, copy, &prepared)?)
            }
            (_, copy, _) => copy,
        };
        st.sequence = sequence;
        let factor_ids: Vec<FactorId> = match ids {
            Some(ids) => ids,
            None => (0..prepared.factors.len() as u64)
                .map(|k| st.next_factor_id + k)
                .collect(),
        };
        st.next_factor_id = factor_ids
            .iter()
            .map(|id| id + 1)
            .fold(st.next_factor_id, u64::max);
        if let (Some(d), Some(copy)) = (durable.as_mut(), wire_copy) {
            d.track(copy.factors, &factor_ids, &prepared);
        }
        // Mirror first: later batches validate against it even while this one waits.
        let mut new_values = Vec::new();
        for v in &prepared.variables {
            let kind = v.value.kind();
            let value = WireValue::from_vec(catalogue::encode_variable(v.value.as_ref()));
            let entry = MirrorEntry {
                kind,
                initial: inspect::position(kind, &value),
                value,
                changed: sequence,
                fixed: v.fixed,
                stamp: v.stamp,
            };
            new_values.push(value_of(v.key, &entry));
            st.mirror_values += heap_values(&entry.value);
            if let Some(old) = st.mirror.insert(v.key, entry) {
                st.mirror_values -= heap_values(&old.value);
            }
        }
        for (key, v) in &prepared.guesses {
            let value = WireValue::from_vec(catalogue::encode_variable(v.as_ref()));
            let added = heap_values(&value);
            let entry = st.mirror.get_mut(key).expect("validated");
            let removed = heap_values(&entry.value);
            entry.initial = inspect::position(entry.kind, &value);
            entry.value = value;
            entry.changed = sequence;
            new_values.push(value_of(*key, entry));
            st.mirror_values = st.mirror_values + added - removed;
        }
        for &(key, fixed) in &prepared.fix {
            st.mirror.get_mut(&key).expect("validated").fixed = fixed;
        }
        st.live_factors.extend(factor_ids.iter().copied());
        for (f, &id) in prepared.factors.iter().zip(&factor_ids) {
            if let Some(edge) = inspect::edge(&st.mirror, f.factor.keys()) {
                st.edges.insert(id, edge);
            }
        }
        for id in &prepared.remove {
            st.live_factors.remove(id);
            st.edges.remove(id);
        }
        let predicted = prepared.predicted.clone();
        if st.problem.is_some() {
            self.apply_prepared(&mut st, sequence, prepared, factor_ids.clone());
        } else {
            st.pending_factors += prepared.factor_count();
            st.pending
                .push_back((sequence, prepared, factor_ids.clone()));
            st.dirty = true;
        }
        let mut ack = BatchAck {
            session: self.name.clone(),
            sequence,
            factor_ids,
            predicted,
            reflected: st.solved_sequence >= sequence,
            producer: None,
            producer_seq: None,
            accepted_through: None,
            duplicate: false,
        };
        if let Some(origin) = &origin {
            st.producers.record(origin, &ack);
            ack.producer = Some(origin.producer.clone());
            ack.producer_seq = Some(origin.seq);
            ack.accepted_through = Some(st.producers.accepted_through(&origin.producer));
        }
        self.maybe_schedule(&mut st);
        let will_solve = st.solved_sequence < sequence && (st.scheduled || st.timer_armed);
        if let (Some(d), true) = (durable.as_mut(), journal) {
            d.maybe_snapshot(self, &st);
        }
        // The fsync runs with the session and its journal unlocked, so the solve just scheduled
        // (and reads) run meanwhile, and the session's next batches are written and share it
        // (group commit, `journal::group_commit`); the acknowledgement below, and everything a
        // solve publishes (it passes `journal_barrier` first), wait for the batch to be durable.
        drop(st);
        let pending = match (durable.as_ref(), journal) {
            (Some(d), true) => Some(d.pending()),
            _ => None,
        };
        drop(durable);
        if let Err(e) = pending.map_or(Ok(()), |p| p.wait(&self.name)) {
            // Nothing is acknowledged; the step-down below takes the session's locks.
            drop(acknowledging);
            return Err(self.sync_refused(e));
        }
        // Batches sharing an fsync may get here in any order.
        self.accepted.send_if_modified(|accepted| {
            std::mem::replace(accepted, sequence.max(*accepted)) < sequence
        });
        // A replay (recovery, adoption) restores what was acknowledged before: acknowledging it
        // again would tell subscribers something new was applied, with a producer's
        // `accepted_through` going backwards. The recovery's solve publishes the estimate.
        if journal {
            self.emit(SessionEvent::Ack(ack.clone()));
        }
        if journal && !new_values.is_empty() {
            self.emit(SessionEvent::Estimate(Estimate {
                session: self.name.clone(),
                sequence,
                variables: new_values,
            }));
        }
        Ok((ack, will_solve))
    }

    /// The answer to a repeat of `origin`'s batch: its original acknowledgement (published again,
    /// so a zenoh producer that lost it hears it), nothing applied.
    fn repeat(&self, st: &State, origin: &Origin, kept: &KeptAck) -> (BatchAck, bool) {
        // The original may still be on its way to the disk.
        self.journal_barrier();
        let mut ack =
            producers::original_ack(kept, &self.name, &origin.producer, st.solved_sequence);
        ack.accepted_through = Some(st.producers.accepted_through(&origin.producer));
        self.emit(SessionEvent::Ack(ack.clone()));
        let will_solve = st.solved_sequence < ack.sequence && (st.scheduled || st.timer_armed);
        (ack, will_solve)
    }

    pub(super) fn check_batch_size(&self, batch: &Batch) -> Result<(), ServiceError> {
        let items = batch.variables.len()
            + batch.factors.len()
            + batch.remove_factors.len()
            + batch.fix.len()
            + batch.unfix.len()
            + batch.guesses.len();
        if items > self.limits.max_batch_items {
            return Err(ServiceError::new(
                ErrorKind::TooLarge,
                "batch_too_large",
                format!(
                    "the batch has {items} items (variables, factors, removals, fixes, guesses); the limit is {} (limits.max_batch_items): split it",
                    self.limits.max_batch_items
                ),
            )
            .at("batch"));
        }
        Ok(())
    }

    pub(super) fn check_session_size(
        &self,
        st: &State,
        prepared: &PreparedBatch,
    ) -> Result<(), ServiceError> {
        let variables = st.mirror.len() + prepared.variables.len();
        if variables > self.limits.max_variables_per_session {
            return Err(ServiceError::invalid(
                "session_full",
                "variables",
                format!(
                    "session `{}` would hold {variables} variables; the limit is {} (limits.max_variables_per_session)",
                    self.name, self.limits.max_variables_per_session
                ),
            ));
        }
        let factors =
            (st.live_factors.len() + prepared.factors.len()).saturating_sub(prepared.remove.len());
        if factors > self.limits.max_factors_per_session {
            return Err(ServiceError::invalid(
                "session_full",
                "factors",
                format!(
                    "session `{}` would hold {factors} factors; the limit is {} (limits.max_factors_per_session)",
                    self.name, self.limits.max_factors_per_session
                ),
            ));
        }
        Ok(())
    }

    /// Applies a validated batch to the problem (present in `st`).
    pub(super) fn apply_prepared(
        &self,
        st: &mut State,
        sequence: u64,
        prepared: PreparedBatch,
        factor_ids: Vec<FactorId>,
    ) {
        let State {
            problem,
            index,
            factor_ids: ids,
            seeds,
            ..
        } = st;
        let problem = problem.as_mut().expect("caller checked");
        let index = index.as_mut().expect("kept with the problem");
        let first_new_factor = problem.factors().len();
        let mut structural = !prepared.remove.is_empty() || !prepared.fix.is_empty();
        let adds_variables = !prepared.variables.is_empty();
        for v in prepared.variables {
            problem.add_variable(v.key, v.value).expect("validated");
            if v.fixed {
                problem.set_fixed(v.key, true).expect("validated");
            }
        }
        let added = prepared.factors.len();
        for (f, id) in prepared.factors.into_iter().zip(factor_ids) {
            // No label: `prepare` checked what the problem's errors would name, and a session's
            // factor is named by its id.
            problem
                .add_checked_factor_sqrt(f.factor, f.sqrt_information, f.robust, String::new())
                .expect("validated");
            ids.push(id);
        }
        // chi2 the new factors add at the current estimate, before removals shift indices.
        let new_chi2 =
            solver::evaluate_chi2(&problem.factors()[first_new_factor..], &problem.values)
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
            structural = true;
        }
        st.factors_since_solve += added;
        st.structural |= structural;
        // A batch that only adds factors whose total chi2 at the current (converged) estimate is
        // below the function tolerance of the whole cannot make a solve gain more than that
        // tolerance: the estimate stays the optimum to within what a solve would reach. This is
        // what makes appending an odometry-predicted pose free.
        if !adds_variables && added == 0 && !structural && !st.dirty {
            // An empty batch: whatever reflected the last one reflects this one (a `wait` on it
            // must not wait for a timer, or for ever under `manual`).
            st.solved_sequence = sequence;
            self.solved.send_replace(sequence);
            return;
        }
        let total = st.chi2.unwrap_or(0.0) + new_chi2;
        let negligible = new_chi2 <= st.options.function_tolerance * total || new_chi2 == 0.0;
        let was_converged = st.converged && !st.dirty && st.chi2.is_some();
        st.chi2 = st.chi2.map(|_| total);
        if was_converged && !structural && negligible {
            st.seeds.clear();
            st.solved_sequence = sequence;
            st.skipped_solves += 1;
            self.solved.send_replace(sequence);
        } else {
            st.dirty = true;
            st.converged = false;
        }
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
        session.lock().sequence = u64::MAX - 1;
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
        assert_eq!(session.lock().sequence, u64::MAX);
        assert!(session.lock().mirror.get(&1).is_none(), "nothing applied");
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
