//! `BlockFactor::refactor` against a dense Cholesky: after every partial refactor (random
//! touched variables, their ancestors, in a random order), `L Lᵀ` equals `H` in the factor's
//! order, whether kept subtrees contribute through their columns or their update matrices, and
//! whether a run of columns is eliminated column by column or as a dense front (the tail among
//! them). And the wildfire back substitution against a full one.

use super::*;

use crate::factors::testing::Rng;

/// A symmetric block matrix: `blocks[(u, v)]` for `u ≥ v` in variable index (row-major du×dv).
struct Sparse {
    dims: Vec<usize>,
    blocks: std::collections::BTreeMap<(usize, usize), Vec<f64>>,
}

impl Sparse {
    /// `H_uv` (du×dv) for any `u, v`, zero when absent.
    fn block(&self, u: usize, v: usize) -> Vec<f64> {
        let (du, dv) = (self.dims[u], self.dims[v]);
        if u >= v {
            self.blocks
                .get(&(u, v))
                .cloned()
                .unwrap_or(vec![0.0; du * dv])
        } else {
            let t = self.block(v, u);
            (0..du * dv).map(|i| t[(i % dv) * du + i / dv]).collect()
        }
    }
    fn neighbours(&self, v: usize) -> Vec<usize> {
        let mut out: Vec<usize> = self
            .blocks
            .keys()
            .filter_map(|&(a, b)| match (a == v, b == v) {
                (true, false) => Some(b),
                (false, true) => Some(a),
                _ => None,
            })
            .collect();
        out.sort_unstable();
        out.dedup();
        out
    }
    /// Adds a random coupling between `u ≠ v`, and to both diagonals enough to stay positive
    /// definite (diagonal dominance).
    fn couple(&mut self, rng: &mut Rng, u: usize, v: usize) {
        let (a, b) = (u.max(v), u.min(v));
        let (da, db) = (self.dims[a], self.dims[b]);
        let block = self.blocks.entry((a, b)).or_insert(vec![0.0; da * db]);
        for x in block.iter_mut() {
            *x += rng.symmetric();
        }
        for (w, d) in [(a, da), (b, db)] {
            let diagonal = self.blocks.entry((w, w)).or_insert(vec![0.0; d * d]);
            for i in 0..d {
                diagonal[i * d + i] += 3.0 * d.max(da.max(db)) as f64;
            }
        }
    }
}

fn refactor(factor: &mut BlockFactor, h: &Sparse, order: &[usize]) {
    let mut in_order = vec![false; h.dims.len()];
    for &v in order {
        in_order[v] = true;
    }
    let reaching = factor.reaching(order, &in_order);
    let kept_roots: Vec<usize> = reaching
        .iter()
        .copied()
        .filter(|&k| factor.parent(k).is_some_and(|p| in_order[p]))
        .collect();
    factor
        .refactor(order, &in_order, &reaching, |r, rank, acc| {
            for (out, x) in acc.diagonal_mut().iter_mut().zip(h.block(r, r)) {
                *out += x;
            }
            for u in h.neighbours(r) {
                if rank[u] > rank[r] {
                    let du = h.dims[u];
                    for (out, x) in acc.block_mut(u, du).iter_mut().zip(h.block(u, r)) {
                        *out += x;
                    }
                }
            }
        })
        .expect("positive definite");
    factor.reparent(&kept_roots);
}

/// max |L Lᵀ − H| over every entry, in the factor's order.
fn reconstruction_error(factor: &BlockFactor, h: &Sparse) -> f64 {
    // The variables with a column (the others are not in the system yet).
    let n = h.dims.len();
    let mut by_rank: Vec<usize> = (0..n)
        .filter(|&v| !factor.columns[v].diagonal.is_empty())
        .collect();
    by_rank.sort_by_key(|&v| factor.rank[v]);
    let mut start = vec![0; n];
    let mut total = 0;
    for &v in &by_rank {
        start[v] = total;
        total += h.dims[v];
    }
    let mut l = vec![0.0; total * total];
    for &v in &by_rank {
        let (d, column) = (h.dims[v], &factor.columns[v]);
        for i in 0..d {
            for j in 0..=i {
                l[(start[v] + i) * total + start[v] + j] = column.diagonal[i * d + j];
            }
        }
        for &(u, o) in &column.rows {
            let (u, du) = (u as usize, h.dims[u as usize]);
            for i in 0..du {
                for j in 0..d {
                    l[(start[u] + i) * total + start[v] + j] =
                        column.blocks[o as usize + i * d + j];
                }
            }
        }
    }
    let mut worst = 0.0f64;
    for &u in &by_rank {
        for &v in &by_rank {
            let hb = h.block(u, v);
            let (du, dv) = (h.dims[u], h.dims[v]);
            for i in 0..du {
                for j in 0..dv {
                    let (a, b) = (start[u] + i, start[v] + j);
                    let llt: f64 = (0..total)
                        .map(|k| l[a * total + k] * l[b * total + k])
                        .sum();
                    worst = worst.max((llt - hb[i * dv + j]).abs());
                }
            }
        }
    }
    worst
}

/// `h` factored from scratch in variable order, checked against the dense Cholesky.
fn factored_from_scratch(h: &Sparse) -> BlockFactor {
    let mut factor = BlockFactor::default();
    factor.grow(&h.dims);
    refactor(&mut factor, h, &(0..h.dims.len()).collect::<Vec<_>>());
    assert!(reconstruction_error(&factor, h) < 1e-9);
    factor
}

#[test]
fn partial_refactors_equal_a_dense_cholesky_and_reuse_kept_subtrees() {
    let mut rng = Rng::new(0x9e37_79b9_7f4a_7c15);
    let n = 48;
    // Poses (3) with a few landmarks (2) among them: blocks of two sizes.
    let dims: Vec<usize> = (0..n).map(|v| if v % 7 == 3 { 2 } else { 3 }).collect();
    let mut h = Sparse {
        dims,
        blocks: Default::default(),
    };
    for v in 1..n {
        h.couple(&mut rng, v - 1, v);
    }
    for _ in 0..2 * n {
        let (u, v) = (rng.below(n), rng.below(n));
        if u != v {
            h.couple(&mut rng, u, v);
        }
    }
    let mut factor = factored_from_scratch(&h);

    assert!(
        factor.dense_columns() > 0,
        "the first factorisation has a dense front"
    );
    let dense_at_start = factor.dense_columns();
    let reused = random_partial_refactors(&mut rng, &mut h, &mut factor, 60, true);
    assert!(reused, "some refactor took a kept subtree's update matrix");
    assert!(
        factor.dense_columns() > dense_at_start,
        "some partial refactor had a dense front"
    );
}

/// `rounds` times: a change at one or two variables (a new coupling, or a diagonal one), then
/// a refactor of the touched variables and their ancestors in a random order (`shuffled`) or in
/// variable order, checked against the dense Cholesky. Returns whether some refactor took a
/// kept subtree's update matrix.
fn random_partial_refactors(
    rng: &mut Rng,
    h: &mut Sparse,
    factor: &mut BlockFactor,
    rounds: usize,
    shuffled: bool,
) -> bool {
    let n = h.dims.len();
    let mut reused = false;
    for _ in 0..rounds {
        // A change at one or two variables (a new coupling, or a diagonal one), then the
        // touched variables and their ancestors in a random order.
        let u = rng.below(n);
        let v = if rng.below(2) == 0 { rng.below(n) } else { u };
        if u != v {
            h.couple(rng, u, v);
        } else {
            h.blocks
                .get_mut(&(u, u))
                .expect("every variable is coupled")[0] += 1.0;
        }
        let mut affected = Vec::new();
        let mut seen = vec![false; n];
        for mut w in [u, v] {
            while !seen[w] {
                seen[w] = true;
                affected.push(w);
                match factor.parent(w) {
                    Some(p) => w = p,
                    None => break,
                }
            }
        }
        // New couplings may join columns that were in different subtrees: their ancestors
        // (in the new structure) are found by the refactor itself; every ancestor of the
        // touched variables in the old tree is in `affected`.
        if shuffled {
            for i in (1..affected.len()).rev() {
                affected.swap(i, rng.below(i + 1));
            }
        } else {
            affected.sort_unstable();
        }
        refactor(factor, h, &affected);
        reused |= factor.kept_update_bytes() > 0;
        let error = reconstruction_error(factor, h);
        assert!(
            error < 1e-9,
            "L Lᵀ − H = {error:e} after refactoring {affected:?}"
        );
    }
    reused
}

#[test]
fn runs_of_a_clique_are_factored_as_dense_fronts() {
    // A band of width 12 in natural order: each column reaches the next 12, so a run of
    // columns forms a clique with the next band beyond it (a front with rows beyond it) all
    // the way down, where a dense tail alone would take only the last dozen columns.
    let mut rng = Rng::new(0x2545_f491_4f6c_dd1d);
    let n = 72;
    let dims: Vec<usize> = (0..n).map(|v| if v % 5 == 2 { 6 } else { 3 }).collect();
    let mut h = Sparse {
        dims,
        blocks: Default::default(),
    };
    for v in 0..n {
        for u in v + 1..(v + 13).min(n) {
            h.couple(&mut rng, u, v);
        }
    }
    let mut factor = factored_from_scratch(&h);
    assert!(
        factor.dense_columns() >= n - 12,
        "{} of {n} columns in dense fronts",
        factor.dense_columns()
    );
    let dense_at_start = factor.dense_columns();
    random_partial_refactors(&mut rng, &mut h, &mut factor, 40, false);
    assert!(
        factor.dense_columns() > dense_at_start,
        "some partial refactor had a front"
    );
    // Every refactor above built its fronts in the buffers of the ones before (and was checked
    // against a dense Cholesky): they are kept for the next.
    assert!(factor.front_scratch_bytes() > 0, "front buffers are kept");
}

/// `Lᵀ x = y` solved in full (every column, threshold 0) from zero.
fn solved_in_full(factor: &mut BlockFactor, offset: &[usize], y: &[f64]) -> Vec<f64> {
    let all = vec![true; offset.len()];
    let (mut x, mut propagated) = (vec![0.0; y.len()], vec![0.0; y.len()]);
    factor.back_substitute(
        &all,
        offset,
        y,
        Solution {
            x: &mut x,
            propagated: &mut propagated,
        },
        0.0,
        &mut Vec::new(),
    );
    x
}

#[test]
fn back_substitution_passes_on_moves_that_add_up_past_the_threshold() {
    // A chain 0-1-…-5 of 3-dim variables factored in order: 5 is the root and every other
    // column's only row is its parent. Each update refactors the root alone and moves its
    // solution by less than the threshold; over many updates the moves add up far past it.
    let mut rng = Rng::new(0x2545_f491_4f6c_dd1d);
    let n = 6;
    let mut h = Sparse {
        dims: vec![3; n],
        blocks: Default::default(),
    };
    for v in 0..n - 1 {
        h.couple(&mut rng, v, v + 1);
        // Coupled strongly (still diagonally dominant), so a child follows its parent's moves.
        for x in h.blocks.get_mut(&(v + 1, v)).expect("coupled") {
            *x *= 2.5;
        }
    }
    let mut factor = factored_from_scratch(&h);
    let offset: Vec<usize> = (0..n).map(|v| 3 * v).collect();
    let mut y: Vec<f64> = (0..3 * n).map(|_| rng.symmetric()).collect();
    let mut x = solved_in_full(&mut factor, &offset, &y);
    let mut propagated = x.clone();
    let threshold = 1e-3;
    let root = 3 * (n - 1)..3 * n;
    let mut root_only = vec![false; n];
    root_only[n - 1] = true;
    let start = x.clone();
    let mut worst_error = 0.0f64;
    for _ in 0..1000 {
        let before = solved_in_full(&mut factor, &offset, &y);
        for r in root.clone() {
            y[r] += 2e-4;
        }
        let exact = solved_in_full(&mut factor, &offset, &y);
        let root_move = root.clone().map(|r| (exact[r] - before[r]).abs());
        assert!(root_move.fold(0.0, f64::max) < threshold);
        factor.back_substitute(
            &root_only,
            &offset,
            &y,
            Solution {
                x: &mut x,
                propagated: &mut propagated,
            },
            threshold,
            &mut Vec::new(),
        );
        let error = x.iter().zip(&exact).map(|(a, b)| (a - b).abs());
        worst_error = worst_error.max(error.fold(0.0, f64::max));
    }
    let exact = solved_in_full(&mut factor, &offset, &y);
    let drift = exact.iter().zip(&start).map(|(a, b)| (a - b).abs());
    let drift = drift.fold(0.0, f64::max);
    assert!(drift > 10.0 * threshold, "the moves add up: {drift}");
    assert!(
        worst_error < 2.0 * threshold,
        "the subtree follows its root within the threshold: off by {worst_error}, the \
         solution drifted {drift}"
    );
}

/// Random rows `W` (`k` of them) on `vars`, as `add_rows` takes them, with `WᵀW` added to `h`.
fn random_rows(rng: &mut Rng, h: &mut Sparse, vars: &[usize], k: usize) -> UpdateRows {
    let scalars: usize = vars.iter().map(|&v| h.dims[v]).sum();
    let transposed: Vec<f64> = (0..scalars * k).map(|_| rng.symmetric()).collect();
    let mut start = Vec::new();
    let mut at = 0;
    for &v in vars {
        start.push(at);
        at += h.dims[v];
    }
    for (a, &u) in vars.iter().enumerate() {
        for (b, &v) in vars.iter().enumerate() {
            if u < v {
                continue;
            }
            let (du, dv) = (h.dims[u], h.dims[v]);
            let block = h.blocks.entry((u, v)).or_insert(vec![0.0; du * dv]);
            for i in 0..du {
                for j in 0..dv {
                    let (ru, rv) = (start[a] + i, start[b] + j);
                    block[i * dv + j] += (0..k)
                        .map(|r| transposed[ru * k + r] * transposed[rv * k + r])
                        .sum::<f64>();
                }
            }
        }
    }
    UpdateRows {
        variables: vars.iter().map(|&v| v as u32).collect(),
        k,
        transposed,
    }
}

#[test]
fn rank_updates_equal_a_dense_cholesky_with_new_columns_and_refactors_between() {
    let mut rng = Rng::new(0x51_7cc1_b727_220a);
    let (n, first_new) = (48, 36);
    let dims: Vec<usize> = (0..n).map(|v| if v % 7 == 3 { 2 } else { 3 }).collect();
    let mut h = Sparse {
        dims: dims.clone(),
        blocks: Default::default(),
    };
    for v in 1..first_new {
        h.couple(&mut rng, v - 1, v);
    }
    for _ in 0..first_new {
        let (u, v) = (rng.below(first_new), rng.below(first_new));
        if u != v {
            h.couple(&mut rng, u, v);
        }
    }
    let mut factor = BlockFactor::default();
    factor.grow(&h.dims);
    refactor(&mut factor, &h, &(0..first_new).collect::<Vec<_>>());
    let offset: Vec<usize> = dims
        .iter()
        .scan(0, |at, &d| {
            *at += d;
            Some(*at - d)
        })
        .collect();
    let scalars: usize = dims.iter().sum();
    let (y, mut partial) = (vec![0.0; scalars], vec![0.0; scalars]);
    let mut updated = 0;
    // A new variable per round (odometry from the newest, a loop closure to an older one: two
    // groups meeting at the new column), then rank updates between old variables with partial
    // refactors between them.
    for round in 0..40 {
        let groups = if first_new + round < n {
            let new = first_new + round;
            factor.append(&[new]);
            let older = rng.below(new - 1);
            vec![
                random_rows(&mut rng, &mut h, &[new - 1, new], 4),
                random_rows(&mut rng, &mut h, &[older, new], 3),
            ]
        } else {
            let (u, v) = (rng.below(n), rng.below(n));
            let vars = if u == v { vec![u] } else { vec![u, v] };
            let k = 1 + rng.below(4);
            vec![random_rows(&mut rng, &mut h, &vars, k)]
        };
        let update = factor
            .add_rows(groups, &offset, &y, &mut partial)
            .expect("positive definite");
        updated += update.path.len();
        let error = reconstruction_error(&factor, &h);
        assert!(error < 1e-9, "L Lᵀ − H = {error:e} after round {round}");
        // Back substitution from the roots reaches every column built so far (a new column
        // became a root, the old root its child), also before a refactor re-roots the top.
        let built = factor
            .columns
            .iter()
            .filter(|c| !c.diagonal.is_empty())
            .count();
        let solved = factor.back_substitute(
            &vec![true; n],
            &offset,
            &y,
            Solution {
                x: &mut vec![0.0; scalars],
                propagated: &mut vec![0.0; scalars],
            },
            0.0,
            &mut Vec::new(),
        );
        assert_eq!(solved, built, "columns solved after round {round}");
        if round >= n - first_new && round % 3 == 0 {
            random_partial_refactors(&mut rng, &mut h, &mut factor, 1, true);
        }
    }
    assert!(
        updated > 40,
        "the updates changed paths ({updated} columns)"
    );
    // Every column is reached from the roots (new columns became roots, old roots their
    // children).
    let all = vec![true; n];
    let (mut x, mut propagated) = (vec![0.0; scalars], vec![0.0; scalars]);
    let solved = factor.back_substitute(
        &all,
        &offset,
        &y,
        Solution {
            x: &mut x,
            propagated: &mut propagated,
        },
        0.0,
        &mut Vec::new(),
    );
    assert_eq!(solved, n);
}
