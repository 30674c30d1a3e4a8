//! Explicit or implicit: whether the reduced system S may be formed. Decided from the reduced
//! graph before anything is allocated: the bytes S and its factor would take (from the camera
//! pairs that share a point) against a limit, by default half the memory the machine has
//! available (the rest holds the problem, H and everything else of the solve); and, when S
//! would fit but fill in to a dense factor, its predicted factorisation time against an
//! implicit step's products (1 000 cameras sharing 300 000 points: 40 s explicit against 8 s
//! implicit for three LM steps).

/// What an explicit S would hold and what forming and factorising it would cost, against an
/// implicit solve's products; counted on the free-variable graph `adjacency` without building
/// the reduced one (see [`ExplicitSize::of`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct ExplicitSize {
    /// Scalar unknowns of S.
    n: u64,
    /// Scalars of S's pattern, lower triangle (diagonal blocks' lower halves included).
    lower: u64,
    /// Pairs of neighbours (either order once, with themselves) over the eliminated blocks:
    /// the elimination's index of S blocks holds one entry per pair.
    pairs: u64,
    /// Multiply-adds of the elimination: Σ over pairs (k, l) of an eliminated block e of
    /// d_k d_e d_l.
    elimination: u64,
    /// Scalars of the W blocks (eliminated × kept): an implicit product reads each twice.
    w_scalars: u64,
}

/// Multiply-adds per second a dense-ish factorisation of S runs at (faer, one core of the
/// 2-core Xeon of `benches/history/issue-57-ba.md`: 1 000 cameras, n = 9 000, in 11 s).
const FACTOR_RATE: f64 = 1e10;
/// Multiply-adds per second of the elimination's small blocks (problem-16: 54 M in 14 ms).
const ELIMINATION_RATE: f64 = 4e9;
/// Multiply-adds per second of an implicit product: memory-bound, every W block read twice
/// (1 000 cameras: 97 M in 0.11 s; 5 000 cameras: 650 M in 0.76 s).
const PRODUCT_RATE: f64 = 8e8;
/// CG iterations an implicit step is assumed to take (measured 9-12 per LM step on the BAL and
/// synthetic problems), with room for the extra LM steps an inexact solve may need.
const CG_PER_STEP: f64 = 20.0;
/// S's pattern at least this full (of the lower triangle) fills in to a dense factor: its
/// factorisation costs n³/6 multiply-adds. Below it the fill is not predicted, and the
/// time-driven choice is not made.
const DENSE_FILL: f64 = 0.5;

impl ExplicitSize {
    /// Counts S for the kept blocks (`eliminate[b]` false) of `adjacency` (see
    /// [`lower_scalars`]).
    pub(super) fn of(adjacency: &[Vec<usize>], eliminate: &[bool], dims: &[usize]) -> Self {
        let kept = |b: &usize| !eliminate[*b];
        let n: u64 = (0..dims.len()).filter(kept).map(|b| dims[b] as u64).sum();
        let lower = lower_scalars(adjacency, eliminate, dims);
        let (mut pairs, mut elimination, mut w_scalars) = (0u64, 0u64, 0u64);
        for b in (0..dims.len()).filter(|&b| eliminate[b]) {
            let m = adjacency[b].len() as u64;
            pairs += m * (m + 1) / 2;
            let de = dims[b] as u64;
            let sum: u64 = adjacency[b].iter().map(|&k| dims[k] as u64).sum();
            let squares: u64 = adjacency[b]
                .iter()
                .map(|&k| (dims[k] * dims[k]) as u64)
                .sum();
            elimination += de * (sum * sum + squares) / 2;
            w_scalars += de * sum;
        }
        Self {
            n,
            lower,
            pairs,
            elimination,
            w_scalars,
        }
    }

    /// Bytes an explicit S would take: its values (dense n², or the sparse pattern's lower
    /// triangle), its factor (dense: in place; sparse: at least the pattern again, fill-in not
    /// counted) and the elimination's index of S blocks (one per pair).
    pub(super) fn bytes(&self, dense: bool) -> u64 {
        let values = if dense {
            self.n * self.n
        } else {
            2 * self.lower
        };
        8 * (values + self.pairs)
    }

    /// `Some(why)` when forming and factorising S is predicted to take more than twice an
    /// implicit step's [`CG_PER_STEP`] products: only for a pattern that fills in to a dense
    /// factor (see [`DENSE_FILL`]), whose cost is then known (1 000 BAL cameras sharing 300 000
    /// points: 12 s explicit against 0.11 s per product).
    pub(super) fn slower_than_implicit(&self) -> Option<String> {
        let n = self.n as f64;
        let full = n * (n + 1.0) / 2.0;
        if n == 0.0 || (self.lower as f64) < DENSE_FILL * full {
            return None;
        }
        let explicit = n * n * n / 6.0 / FACTOR_RATE + self.elimination as f64 / ELIMINATION_RATE;
        let implicit = CG_PER_STEP * 2.0 * self.w_scalars as f64 / PRODUCT_RATE;
        (explicit > 2.0 * implicit).then(|| {
            format!(
                "auto: forming and factorising the reduced system ({} unknowns, {:.0} % full) is predicted at {:.2} s per step, conjugate gradients at {:.2} s",
                self.n,
                100.0 * self.lower as f64 / full,
                explicit,
                implicit
            )
        })
    }
}

/// Kept blocks up to which S's block pattern is counted in a bit per block pair (8 MiB at
/// most); beyond, by marking each kept block's reduced neighbours.
const PAIR_BITS_MAX: usize = 8192;

/// Scalars of S's pattern, lower triangle: a kept block's reduced neighbours are its kept
/// neighbours and those of its eliminated ones.
fn lower_scalars(adjacency: &[Vec<usize>], eliminate: &[bool], dims: &[usize]) -> u64 {
    let kept = eliminate.iter().filter(|&&e| !e).count();
    if kept <= PAIR_BITS_MAX {
        lower_by_pair_bits(adjacency, eliminate, dims)
    } else {
        lower_by_marking(adjacency, eliminate, dims)
    }
}

/// [`lower_scalars`] by one bit per pair of kept blocks, set from each eliminated block's
/// neighbours in turn: one pass over the eliminated blocks in memory order (5 000 cameras
/// sharing 2 M points: 0.2 s, where marking from each camera jumps between the points' lists
/// at a cache miss each, 1.7 s).
fn lower_by_pair_bits(adjacency: &[Vec<usize>], eliminate: &[bool], dims: &[usize]) -> u64 {
    let kept: Vec<usize> = (0..dims.len()).filter(|&b| !eliminate[b]).collect();
    let mut index = vec![usize::MAX; dims.len()];
    for (i, &b) in kept.iter().enumerate() {
        index[b] = i;
    }
    let m = kept.len();
    let mut bits = vec![0u64; (m * m).div_ceil(64)];
    let mut set = |i: usize, j: usize| {
        let at = i.max(j) * m + i.min(j);
        bits[at / 64] |= 1 << (at % 64);
    };
    let mut around = Vec::new();
    for (b, neighbours) in adjacency.iter().enumerate() {
        if eliminate[b] {
            around.clear();
            around.extend(
                neighbours
                    .iter()
                    .filter(|&&k| !eliminate[k])
                    .map(|&k| index[k]),
            );
            for (t, &i) in around.iter().enumerate() {
                for &j in &around[..t] {
                    set(i, j);
                }
            }
        } else {
            for &k in neighbours.iter().filter(|&&k| !eliminate[k]) {
                set(index[b], index[k]);
            }
        }
    }
    let mut lower = 0u64;
    for (i, &x) in kept.iter().enumerate() {
        let dx = dims[x] as u64;
        lower += dx * (dx + 1) / 2;
        for (j, &y) in kept[..i].iter().enumerate() {
            let at = i * m + j;
            if bits[at / 64] >> (at % 64) & 1 == 1 {
                lower += dx * dims[y] as u64;
            }
        }
    }
    lower
}

/// [`lower_scalars`] by marking, for each kept block, its reduced neighbours before it once each.
fn lower_by_marking(adjacency: &[Vec<usize>], eliminate: &[bool], dims: &[usize]) -> u64 {
    let mut marked = vec![usize::MAX; dims.len()];
    let mut lower = 0u64;
    for x in (0..dims.len()).filter(|&b| !eliminate[b]) {
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
    lower
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
        let size = ExplicitSize::of(&adjacency, &eliminate, &dims);
        let sparse = size.bytes(false);
        assert_eq!(sparse, 8 * (2 * (4 * 45 + 3 * 81) + 3 + 3 + 6));
        assert_eq!(size.bytes(true), 8 * (36 * 36 + 12));
        // Points 2 and 3: pairs (0,0) (0,1) (1,1), 3·9·9 each; point 4 adds three cameras.
        assert_eq!(size.elimination, 2 * 3 * 3 * 81 + 6 * 3 * 81);
        assert_eq!(size.w_scalars, 3 * (18 + 18 + 27));
        assert!(too_big(sparse, Some(sparse)).is_none());
        let why = too_big(sparse, Some(100)).expect("above the limit");
        assert!(why.contains("above"), "{why}");
        assert!(too_big(u64::MAX, None).is_none());
        assert_eq!(explicit_limit(Some(10)), Some(10));
    }

    /// BAL-like graphs: `cameras` of 9 dimensions, then one 3-dimensional point per pair of
    /// cameras `seen(i, j)` says share one.
    fn cameras_and_points(
        cameras: usize,
        seen: impl Fn(usize, usize) -> bool,
    ) -> (Vec<Vec<usize>>, Vec<bool>, Vec<usize>) {
        let mut adjacency = vec![Vec::new(); cameras];
        for i in 0..cameras {
            for j in i + 1..cameras {
                if seen(i, j) {
                    let point = adjacency.len();
                    adjacency.push(vec![i, j]);
                    adjacency[i].push(point);
                    adjacency[j].push(point);
                }
            }
        }
        let eliminate = (0..adjacency.len()).map(|b| b >= cameras).collect();
        let dims = (0..adjacency.len())
            .map(|b| if b < cameras { 9 } else { 3 })
            .collect();
        (adjacency, eliminate, dims)
    }

    /// Both ways of counting S's pattern agree, on graphs with kept blocks adjacent to each
    /// other as well as through eliminated ones.
    #[test]
    fn pair_bits_and_marking_count_the_same_pattern() {
        let (mut adjacency, mut eliminate, mut dims) =
            cameras_and_points(40, |i, j| (i * 7 + j * 3) % 5 == 0);
        // Two kept blocks (6-dimensional) linked directly and to cameras 0 and 1.
        let (a, b) = (adjacency.len(), adjacency.len() + 1);
        adjacency.extend([vec![b, 0], vec![a, 1]]);
        adjacency[0].push(a);
        adjacency[1].push(b);
        eliminate.extend([false, false]);
        dims.extend([6, 6]);
        let marking = lower_by_marking(&adjacency, &eliminate, &dims);
        assert_eq!(lower_by_pair_bits(&adjacency, &eliminate, &dims), marking);
        assert!(marking > 42 * 45, "{marking}");
    }

    #[test]
    fn only_a_big_dense_reduced_system_is_left_to_conjugate_gradients() {
        // 300 cameras, every pair sharing a point: S (2 700 unknowns) is full, and its
        // factorisation costs more than 40 products over 44 850 points.
        let (adjacency, eliminate, dims) = cameras_and_points(300, |_, _| true);
        let size = ExplicitSize::of(&adjacency, &eliminate, &dims);
        let why = size.slower_than_implicit().expect("implicit");
        assert!(why.contains("2700 unknowns, 100 % full"), "{why}");
        // 60 cameras: S (540 unknowns) factorises in less time than the products would take.
        let (adjacency, eliminate, dims) = cameras_and_points(60, |_, _| true);
        assert_eq!(
            ExplicitSize::of(&adjacency, &eliminate, &dims).slower_than_implicit(),
            None
        );
        // 300 cameras in a chain: S is banded, its fill is not predicted, it stays explicit.
        let (adjacency, eliminate, dims) = cameras_and_points(300, |i, j| j == i + 1);
        assert_eq!(
            ExplicitSize::of(&adjacency, &eliminate, &dims).slower_than_implicit(),
            None
        );
    }
}
