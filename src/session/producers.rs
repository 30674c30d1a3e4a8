//! Exactly-once ingest: every producer's progress in a session, and the acknowledgements a
//! repeat is answered with.
//!
//! A batch may name its `producer` and that producer's own counter `producer_seq` (1, 2, 3, …).
//! The session applies number `n` only right after `n − 1`: a repeat (a resend after a lost
//! acknowledgement, a timeout, a reconnection or a restart) is answered with its original
//! acknowledgement and applied no second time; a gap is refused, naming the number expected.
//! The table is part of the session's durable state: batches are journalled with their producer
//! fields (the replay rebuilds it) and snapshots keep it, so a repeat is recognised across
//! restarts and across a failover to another instance reading the same journal.
//!
//! The last [`KEPT_ACKS`] acknowledgements of each producer are kept (a client keeps fewer
//! unacknowledged batches than that); an older repeat is refused as `producer_sequence_forgotten`
//! (it was applied, long ago).

use std::collections::{BTreeMap, HashMap, VecDeque};

use crate::api::wire::{Batch, BatchAck, FactorId};
use crate::api::ServiceError;
use crate::journal::{KeptAck, ProducerRecord};

/// Acknowledgements kept per producer for repeats.
pub(super) const KEPT_ACKS: usize = 1024;
/// The longest producer id.
const MAX_PRODUCER_LEN: usize = 64;

#[derive(Default)]
pub(super) struct Producers {
    by_id: HashMap<String, Producer>,
    /// Estimated bytes held (ids, kept acknowledgements).
    bytes: usize,
}

#[derive(Default)]
struct Producer {
    accepted_through: u64,
    acks: VecDeque<KeptAck>,
}

/// A batch's producer fields, checked.
#[derive(Clone, Debug, PartialEq)]
pub struct Origin {
    pub producer: String,
    pub seq: u64,
}

/// What to do with a batch that names its producer.
pub(super) enum Admission {
    /// The next number: apply it.
    Next,
    /// Applied before: answer with this (its original acknowledgement).
    Repeat(KeptAck),
}

impl Origin {
    /// The producer fields of `batch`: both or neither, a valid id, a number from 1.
    pub fn of(batch: &Batch) -> Result<Option<Origin>, ServiceError> {
        match (&batch.producer, batch.producer_seq) {
            (None, None) => Ok(None),
            (Some(_), None) => Err(ServiceError::bad_request(
                "missing_producer_seq",
                "producer_seq",
                "a batch with a `producer` needs its `producer_seq` (1, 2, 3, …)",
            )),
            (None, Some(_)) => Err(ServiceError::bad_request(
                "missing_producer",
                "producer",
                "a batch with a `producer_seq` needs the `producer` it counts for",
            )),
            (Some(producer), Some(seq)) => {
                check_producer_id(producer, "producer")?;
                if seq == 0 {
                    return Err(ServiceError::bad_request(
                        "invalid_producer_seq",
                        "producer_seq",
                        "producer sequence numbers start at 1",
                    ));
                }
                Ok(Some(Origin {
                    producer: producer.clone(),
                    seq,
                }))
            }
        }
    }
}

/// A valid producer id (`field`: where the request carries it): 400 `invalid_producer`.
pub fn check_producer_id(producer: &str, field: &str) -> Result<(), ServiceError> {
    let valid = !producer.is_empty()
        && producer.len() <= MAX_PRODUCER_LEN
        && producer
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b"._-".contains(&b));
    if valid {
        return Ok(());
    }
    Err(ServiceError::bad_request(
        "invalid_producer",
        field,
        format!("a producer id has 1 to {MAX_PRODUCER_LEN} characters of A-Z a-z 0-9 . _ -"),
    ))
}

impl Producers {
    /// Whether `origin`'s batch is the producer's next (409 for a gap, or a repeat whose
    /// acknowledgement is no longer kept).
    /// A producer not seen before is refused (422 `too_many_producers`) when the session
    /// already counts `max_producers`: each one is kept for good (its acknowledgements are in
    /// every snapshot).
    pub(super) fn admit(
        &self,
        session: &str,
        origin: &Origin,
        max_producers: usize,
    ) -> Result<Admission, ServiceError> {
        let through = self.accepted_through(&origin.producer);
        if !self.by_id.contains_key(&origin.producer) && self.by_id.len() >= max_producers {
            return Err(ServiceError::invalid(
                "too_many_producers",
                "producer",
                format!(
                    "session `{session}` already counts {} producers, its maximum \
                     (limits.max_producers_per_session); a new producer id is refused",
                    self.by_id.len()
                ),
            ));
        }
        if origin.seq == through + 1 {
            return Ok(Admission::Next);
        }
        if origin.seq > through {
            let applied = match through {
                0 => "none of its batches".to_string(),
                1 => "its batch 1".to_string(),
                n => format!("its batches 1 to {n}"),
            };
            return Err(ServiceError::conflict(
                "producer_sequence_gap",
                format!(
                    "session `{session}` expects batch {} of producer `{}` next (it has applied \
                     {applied}); {} would leave a gap: send the missing ones first",
                    through + 1,
                    origin.producer,
                    origin.seq
                ),
            )
            .at("producer_seq"));
        }
        let kept = self.by_id.get(&origin.producer).and_then(|p| {
            let first = p.acks.front()?.producer_seq;
            p.acks
                .get(usize::try_from(origin.seq.checked_sub(first)?).ok()?)
        });
        match kept {
            Some(ack) if ack.producer_seq == origin.seq => Ok(Admission::Repeat(ack.clone())),
            _ => Err(ServiceError::conflict(
                "producer_sequence_forgotten",
                format!(
                    "batch {} of producer `{}` was applied to session `{session}` long ago; only \
                     the acknowledgements of its last {KEPT_ACKS} batches are kept",
                    origin.seq, origin.producer
                ),
            )
            .at("producer_seq")),
        }
    }

    /// Records an applied batch of `origin` (acknowledged with `ack`). Numbers at or below the
    /// producer's progress are already recorded (a journal replayed onto a snapshot that holds
    /// them) and change nothing.
    pub(super) fn record(&mut self, origin: &Origin, ack: &BatchAck) {
        let producer = match self.by_id.get_mut(&origin.producer) {
            Some(p) => p,
            None => {
                self.bytes += PRODUCER_BYTES + origin.producer.len();
                self.by_id.entry(origin.producer.clone()).or_default()
            }
        };
        if origin.seq <= producer.accepted_through {
            return;
        }
        // After a refused gap nothing is recorded, so numbers arrive in order; a journal written
        // by an older build holds no numbers at all.
        if origin.seq != producer.accepted_through + 1 {
            producer.acks.clear();
        }
        producer.accepted_through = origin.seq;
        let kept = KeptAck {
            producer_seq: origin.seq,
            sequence: ack.sequence,
            factor_ids: runs(&ack.factor_ids),
            predicted: ack.predicted.clone(),
        };
        self.bytes += kept_bytes(&kept);
        producer.acks.push_back(kept);
        if producer.acks.len() > KEPT_ACKS {
            let old = producer.acks.pop_front().expect("longer than the bound");
            self.bytes -= kept_bytes(&old);
        }
    }

    pub(super) fn accepted_through(&self, producer: &str) -> u64 {
        self.by_id.get(producer).map_or(0, |p| p.accepted_through)
    }

    /// The session sequence of the producer's last applied batch (0: none).
    pub(super) fn last_sequence(&self, producer: &str) -> u64 {
        self.by_id
            .get(producer)
            .and_then(|p| p.acks.back())
            .map_or(0, |a| a.sequence)
    }

    /// Every producer's `accepted_through`.
    pub(super) fn progress(&self) -> BTreeMap<String, u64> {
        self.by_id
            .iter()
            .map(|(id, p)| (id.clone(), p.accepted_through))
            .collect()
    }

    pub(super) fn bytes(&self) -> usize {
        self.bytes
    }

    /// What a snapshot keeps.
    pub(super) fn records(&self) -> Vec<ProducerRecord> {
        let mut records: Vec<ProducerRecord> = self
            .by_id
            .iter()
            .map(|(id, p)| ProducerRecord {
                producer: id.clone(),
                accepted_through: p.accepted_through,
                acks: p.acks.iter().cloned().collect(),
            })
            .collect();
        records.sort_by(|a, b| a.producer.cmp(&b.producer));
        records
    }

    /// The table a snapshot kept.
    pub(super) fn from_records(records: Vec<ProducerRecord>) -> Self {
        let mut producers = Producers::default();
        for record in records {
            producers.bytes += PRODUCER_BYTES
                + record.producer.len()
                + record.acks.iter().map(kept_bytes).sum::<usize>();
            producers.by_id.insert(
                record.producer,
                Producer {
                    accepted_through: record.accepted_through,
                    acks: record.acks.into(),
                },
            );
        }
        producers
    }
}

/// The original acknowledgement `kept` of a repeat, marked `duplicate`, with `reflected` as of
/// now (`reflected`: the sequence the estimate reflects) and without `accepted_through` (the
/// caller sets the current one).
pub(super) fn original_ack(
    kept: &KeptAck,
    session: &str,
    producer: &str,
    reflected: u64,
) -> BatchAck {
    BatchAck {
        session: session.to_string(),
        sequence: kept.sequence,
        factor_ids: kept
            .factor_ids
            .iter()
            .flat_map(|&[first, count]| first..first + count)
            .collect(),
        predicted: kept.predicted.clone(),
        reflected: reflected >= kept.sequence,
        producer: Some(producer.to_string()),
        producer_seq: Some(kept.producer_seq),
        accepted_through: None,
        duplicate: true,
    }
}

/// Consecutive ids as `[first, count]` runs.
fn runs(ids: &[FactorId]) -> Vec<[u64; 2]> {
    let mut runs: Vec<[u64; 2]> = Vec::new();
    for &id in ids {
        match runs.last_mut() {
            Some([first, count]) if *first + *count == id => *count += 1,
            _ => runs.push([id, 1]),
        }
    }
    runs
}

const PRODUCER_BYTES: usize = std::mem::size_of::<(String, Producer)>() + 48;

fn kept_bytes(ack: &KeptAck) -> usize {
    std::mem::size_of::<KeptAck>() + 16 * ack.factor_ids.len() + 8 * ack.predicted.len()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ack(sequence: u64, ids: Vec<u64>) -> BatchAck {
        BatchAck {
            session: "s".into(),
            sequence,
            factor_ids: ids,
            predicted: vec![7],
            reflected: false,
            producer: None,
            producer_seq: None,
            accepted_through: None,
            duplicate: false,
        }
    }

    fn origin(seq: u64) -> Origin {
        Origin {
            producer: "robot-1".into(),
            seq,
        }
    }

    #[test]
    fn a_new_producer_beyond_the_maximum_is_refused() {
        let mut p = Producers::default();
        for id in ["a", "b"] {
            let o = Origin {
                producer: id.into(),
                seq: 1,
            };
            assert!(matches!(p.admit("s", &o, 2), Ok(Admission::Next)));
            p.record(&o, &ack(1, vec![]));
        }
        let new = Origin {
            producer: "c".into(),
            seq: 1,
        };
        let refused = p.admit("s", &new, 2).err().unwrap();
        assert_eq!(refused.body.code, "too_many_producers");
        let known = Origin {
            producer: "a".into(),
            seq: 2,
        };
        assert!(matches!(p.admit("s", &known, 2), Ok(Admission::Next)));
    }

    #[test]
    fn the_next_number_is_admitted_a_repeat_gets_its_ack_a_gap_is_refused() {
        let mut p = Producers::default();
        assert!(matches!(p.admit("s", &origin(1), 8), Ok(Admission::Next)));
        assert_eq!(
            p.admit("s", &origin(2), 8).err().unwrap().body.code,
            "producer_sequence_gap"
        );
        p.record(&origin(1), &ack(5, vec![10, 11, 12]));
        p.record(&origin(2), &ack(6, vec![13, 20]));
        let Ok(Admission::Repeat(kept)) = p.admit("s", &origin(1), 8) else {
            panic!("a repeat")
        };
        let again = original_ack(&kept, "s", "robot-1", 5);
        assert_eq!(again.factor_ids, vec![10, 11, 12]);
        assert_eq!(
            (again.sequence, again.reflected, again.duplicate),
            (5, true, true)
        );
        let Ok(Admission::Repeat(kept)) = p.admit("s", &origin(2), 8) else {
            panic!("a repeat")
        };
        assert_eq!(kept.factor_ids, vec![[13, 1], [20, 1]]);
        let gap = p.admit("s", &origin(4), 8).err().unwrap();
        assert_eq!(gap.body.field.as_deref(), Some("producer_seq"));
        assert!(
            gap.body.message.contains("expects batch 3"),
            "{}",
            gap.body.message
        );
        assert_eq!(p.accepted_through("robot-1"), 2);
        assert_eq!(p.last_sequence("robot-1"), 6);
    }

    #[test]
    fn old_repeats_are_forgotten_and_memory_is_bounded() {
        let mut p = Producers::default();
        for seq in 1..=(KEPT_ACKS as u64 + 10) {
            p.record(&origin(seq), &ack(seq, vec![seq]));
        }
        let bytes = p.bytes();
        assert_eq!(
            p.admit("s", &origin(3), 8).err().unwrap().body.code,
            "producer_sequence_forgotten"
        );
        assert!(matches!(
            p.admit("s", &origin(11), 8),
            Ok(Admission::Repeat(_))
        ));
        p.record(&origin(KEPT_ACKS as u64 + 11), &ack(9, vec![1]));
        assert_eq!(p.bytes(), bytes, "a full window stays the same size");
        let back = Producers::from_records(p.records());
        assert_eq!(back.bytes(), p.bytes());
        assert_eq!(back.records(), p.records());
    }

    #[test]
    fn replayed_numbers_at_or_below_the_progress_change_nothing() {
        let mut p = Producers::default();
        p.record(&origin(1), &ack(1, vec![0]));
        p.record(&origin(2), &ack(2, vec![1]));
        let before = p.records();
        p.record(&origin(2), &ack(9, vec![5]));
        assert_eq!(p.records(), before);
    }

    #[test]
    fn producer_fields_come_both_or_neither_and_well_formed() {
        let batch = |producer: Option<&str>, seq: Option<u64>| Batch {
            producer: producer.map(str::to_string),
            producer_seq: seq,
            ..Batch::default()
        };
        assert_eq!(Origin::of(&batch(None, None)).unwrap(), None);
        assert_eq!(
            Origin::of(&batch(Some("r.1_a-b"), Some(1))).unwrap(),
            Some(Origin {
                producer: "r.1_a-b".into(),
                seq: 1
            })
        );
        for (b, field) in [
            (batch(Some("r"), None), "producer_seq"),
            (batch(None, Some(1)), "producer"),
            (batch(Some("a/b"), Some(1)), "producer"),
            (batch(Some(""), Some(1)), "producer"),
            (batch(Some(&"x".repeat(65)), Some(1)), "producer"),
            (batch(Some("r"), Some(0)), "producer_seq"),
        ] {
            let e = Origin::of(&b).unwrap_err();
            assert_eq!(e.body.field.as_deref(), Some(field), "{}", e.body.message);
        }
    }
}
