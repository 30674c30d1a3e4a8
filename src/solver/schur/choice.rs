//! Explicit or implicit: whether the reduced system S may be formed. Decided from the reduced
//! graph before anything is allocated: the bytes S and its factor would take (from the camera
//! pairs that share a point) against a limit, by default half the memory the machine has
//! available (the rest holds the problem, H and everything else of the solve).

/// Bytes an explicit S would take: its values (dense n², or the sparse pattern's lower
/// triangle), its factor (dense: in place; sparse: at least the pattern again, fill-in not
/// counted) and the elimination's index of S blocks (one per neighbour pair of each eliminated
/// block). `reduced_adjacency` and `reduced_dims` in the reduced graph's numbering;
/// `eliminated_neighbours`: each eliminated block's neighbour count.
pub(super) fn explicit_bytes(
    reduced_adjacency: &[Vec<usize>],
    reduced_dims: &[usize],
    eliminated_neighbours: impl Iterator<Item = usize>,
    dense: bool,
) -> u64 {
    let n: u64 = reduced_dims.iter().map(|&d| d as u64).sum();
    let values = if dense {
        n * n
    } else {
        let mut lower = 0u64;
        for (k, around) in reduced_adjacency.iter().enumerate() {
            let dk = reduced_dims[k] as u64;
            lower += dk * (dk + 1) / 2;
            lower += around
                .iter()
                .filter(|&&l| l < k)
                .map(|&l| dk * reduced_dims[l] as u64)
                .sum::<u64>();
        }
        2 * lower
    };
    let pairs: u64 = eliminated_neighbours
        .map(|m| (m * (m + 1) / 2) as u64)
        .sum();
    8 * (values + pairs)
}

/// `Some(why)` when `bytes` exceed `limit` (`None`: the limit is unknown and S is formed, as
/// before this choice existed).
pub(super) fn too_big(bytes: u64, limit: Option<u64>) -> Option<String> {
    let limit = limit?;
    (bytes > limit).then(|| {
        format!(
            "auto: an explicit reduced system would take {:.1} GB (S and its factor), above the {:.1} GB allowed",
            bytes as f64 / 1e9,
            limit as f64 / 1e9
        )
    })
}

/// The bytes an explicit S may take: half the machine's available memory (`MemAvailable`),
/// and no more than the solve's own memory limit when it has one.
pub fn explicit_limit(solve_limit: Option<u64>) -> Option<u64> {
    let available = available_memory_bytes().map(|bytes| bytes / 2);
    match (available, solve_limit) {
        (Some(a), Some(s)) => Some(a.min(s)),
        (a, s) => a.or(s),
    }
}

/// `MemAvailable` of `/proc/meminfo`, where it can be read.
fn available_memory_bytes() -> Option<u64> {
    let meminfo = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = meminfo.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn explicit_bytes_count_the_pattern_the_factor_and_the_pair_index() {
        // Two 9-dimensional cameras sharing points: lower triangle 45 + 45 + 81 values.
        let adjacency = vec![vec![1], vec![0]];
        let sparse = explicit_bytes(&adjacency, &[9, 9], [2, 2, 2].into_iter(), false);
        assert_eq!(sparse, 8 * (2 * 171 + 3 * 3));
        let dense = explicit_bytes(&adjacency, &[9, 9], [2].into_iter(), true);
        assert_eq!(dense, 8 * (18 * 18 + 3));
        assert!(too_big(sparse, Some(sparse)).is_none());
        let why = too_big(sparse, Some(100)).expect("above the limit");
        assert!(why.contains("above"), "{why}");
        assert!(too_big(u64::MAX, None).is_none());
        assert_eq!(explicit_limit(Some(10)), Some(10));
    }
}
