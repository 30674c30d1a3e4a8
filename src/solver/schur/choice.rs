//! Explicit or implicit: whether the reduced system S may be formed. Decided from the reduced
//! graph before anything is allocated: the bytes S and its factor would take (from the camera
//! pairs that share a point) against a limit, by default half the memory the machine has
//! available (the rest holds the problem, H and everything else of the solve).

/// Bytes an explicit S would take: its values (dense n², or the sparse pattern's lower
/// triangle), its factor (dense: in place; sparse: at least the pattern again, fill-in not
/// counted) and the elimination's index of S blocks (one per neighbour pair of each eliminated
/// block). Counted on the free-variable graph `adjacency` without building the reduced one: a
/// kept block's reduced neighbours are its kept neighbours and those of its eliminated ones,
/// marked once each (5 000 cameras sharing 2 M points: a pass over the 12 M observations'
/// pairs, where the reduced graph would list 60 M entries before deduplication).
pub(super) fn explicit_bytes(
    adjacency: &[Vec<usize>],
    eliminate: &[bool],
    dims: &[usize],
    dense: bool,
) -> u64 {
    let kept = |b: &usize| !eliminate[*b];
    let n: u64 = (0..dims.len()).filter(kept).map(|b| dims[b] as u64).sum();
    let values = if dense {
        n * n
    } else {
        let mut marked = vec![usize::MAX; dims.len()];
        let mut lower = 0u64;
        for x in (0..dims.len()).filter(kept) {
            let dx = dims[x] as u64;
            lower += dx * (dx + 1) / 2;
            for &a in &adjacency[x] {
                let around: &[usize] = if eliminate[a] {
                    &adjacency[a]
                } else {
                    std::slice::from_ref(&a)
                };
                for &y in around {
                    if y < x && !eliminate[y] && marked[y] != x {
                        marked[y] = x;
                        lower += dx * dims[y] as u64;
                    }
                }
            }
        }
        2 * lower
    };
    let pairs: u64 = (0..dims.len())
        .filter(|&b| eliminate[b])
        .map(|b| {
            let m = adjacency[b].len() as u64;
            m * (m + 1) / 2
        })
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
        // Cameras 0, 1 (9-dimensional) sharing points 2, 3, 4 (eliminated); camera 5 sees
        // point 4 too, camera 6 nothing: lower triangle 4·45 + (0,1) (0,5) (1,5) pairs.
        let mut adjacency = vec![vec![2, 3, 4], vec![2, 3, 4], vec![0, 1], vec![0, 1]];
        adjacency.extend([vec![0, 1, 5], vec![4], vec![]]);
        let eliminate = [false, false, true, true, true, false, false];
        let dims = [9, 9, 3, 3, 3, 9, 9];
        let sparse = explicit_bytes(&adjacency, &eliminate, &dims, false);
        assert_eq!(sparse, 8 * (2 * (4 * 45 + 3 * 81) + 3 + 3 + 6));
        let dense = explicit_bytes(&adjacency, &eliminate, &dims, true);
        assert_eq!(dense, 8 * (36 * 36 + 12));
        assert!(too_big(sparse, Some(sparse)).is_none());
        let why = too_big(sparse, Some(100)).expect("above the limit");
        assert!(why.contains("above"), "{why}");
        assert!(too_big(u64::MAX, None).is_none());
        assert_eq!(explicit_limit(Some(10)), Some(10));
    }
}
