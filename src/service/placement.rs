//! Where a session lives in a fleet: rendezvous (highest-random-weight) hashing of the session
//! name with every live instance's id. Each instance computes the same owner from the same live
//! set, with no coordination; when an instance leaves, only its sessions move (each to the
//! instance with its next-highest weight), and when one joins, only the sessions it now wins
//! move to it (about 1/n of them).
//!
//! The hash must be the same in every process and every build (std's `DefaultHasher` is not
//! promised to be): FNV-1a over the name, a separator byte and the instance id, then the
//! splitmix64 finaliser so that names differing in their last byte still spread evenly.

/// The instance among `instances` that owns `session`; `None` when there is none. Ties (equal
/// weights, in practice never) go to the larger instance id, so every caller agrees.
pub fn owner<'a, I>(session: &str, instances: I) -> Option<&'a str>
where
    I: IntoIterator<Item = &'a str>,
{
    instances
        .into_iter()
        .map(|instance| (weight(session, instance), instance))
        .max()
        .map(|(_, instance)| instance)
}

/// The weight of `instance` for `session`: stable across processes, builds and platforms.
pub fn weight(session: &str, instance: &str) -> u64 {
    const OFFSET: u64 = 0xcbf2_9ce4_8422_2325;
    const PRIME: u64 = 0x0000_0100_0000_01b3;
    let mut h = OFFSET;
    // 0xff never occurs in UTF-8, so ("ab", "c") and ("a", "bc") hash apart.
    for &b in session
        .as_bytes()
        .iter()
        .chain(&[0xff])
        .chain(instance.as_bytes())
    {
        h ^= u64::from(b);
        h = h.wrapping_mul(PRIME);
    }
    mix(h)
}

/// splitmix64's finaliser: every input bit reaches every output bit.
fn mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    fn names(n: usize) -> Vec<String> {
        (0..n).map(|i| format!("robot-{i}")).collect()
    }

    fn placement<'a>(sessions: &[String], instances: &[&'a str]) -> HashMap<String, &'a str> {
        sessions
            .iter()
            .map(|s| (s.clone(), owner(s, instances.iter().copied()).unwrap()))
            .collect()
    }

    #[test]
    fn the_hash_is_fixed_forever() {
        // Instances of different builds must agree: these values may never change.
        assert_eq!(weight("robot-1", "a"), weight("robot-1", "a"));
        assert_ne!(weight("ab", "c"), weight("a", "bc"));
        assert_eq!(weight("s1", "factord-1"), 0x5a2d_a0df_fc03_be61);
        assert_eq!(owner("s1", ["x", "y", "z"]), Some("z"));
    }

    #[test]
    fn no_instances_no_owner_and_one_instance_owns_everything() {
        assert_eq!(owner("s1", std::iter::empty::<&str>()), None);
        assert!(names(100)
            .iter()
            .all(|s| owner(s, ["only"]) == Some("only")));
    }

    #[test]
    fn sessions_spread_evenly() {
        let sessions = names(6000);
        let instances = ["factord-a", "factord-b", "factord-c"];
        let placed = placement(&sessions, &instances);
        for i in instances {
            let n = placed.values().filter(|o| **o == i).count();
            // 2000 expected; a binomial's standard deviation is ~37.
            assert!((1850..=2150).contains(&n), "{i} owns {n} of 6000");
        }
        // Names that differ only in their last character spread too.
        let similar: Vec<String> = (0..30).map(|i| format!("r{i}")).collect();
        let placed = placement(&similar, &instances);
        for i in instances {
            assert!(placed.values().any(|o| *o == i), "{i} owns none of r0..r29");
        }
    }

    #[test]
    fn when_an_instance_leaves_only_its_sessions_move() {
        let sessions = names(3000);
        let before = placement(&sessions, &["a", "b", "c", "d"]);
        let after = placement(&sessions, &["a", "b", "d"]);
        let mut moved_to = HashMap::new();
        for s in &sessions {
            if before[s] != "c" {
                assert_eq!(before[s], after[s], "{s} moved though its owner stayed");
            } else {
                *moved_to.entry(after[s]).or_insert(0) += 1;
            }
        }
        // c's sessions spread over the three survivors, not onto one.
        assert_eq!(moved_to.len(), 3, "{moved_to:?}");
        assert!(moved_to.values().all(|n| *n > 150), "{moved_to:?}");
    }

    #[test]
    fn when_an_instance_joins_only_the_sessions_it_wins_move_to_it() {
        let sessions = names(3000);
        let before = placement(&sessions, &["a", "b", "c"]);
        let after = placement(&sessions, &["a", "b", "c", "e"]);
        let moved: Vec<_> = sessions
            .iter()
            .filter(|s| before[*s] != after[*s])
            .collect();
        assert!(moved.iter().all(|s| after[*s] == "e"));
        // About a quarter: 750 expected.
        assert!((650..=850).contains(&moved.len()), "{} moved", moved.len());
    }
}
