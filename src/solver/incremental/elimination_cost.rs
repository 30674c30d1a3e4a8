//! What eliminating a graph in a given order costs, from its symbolic factorisation alone:
//! the elimination tree, then the factor's rows by row subtrees (the batch solve's analysis in
//! [`crate::solver::supernodes`] does the same on its blocks). Time is that of the factor's
//! nonzero count, memory linear in the vertices; no structure is stored.

use crate::solver::supernodes::{elimination_tree, visit_factor_rows};

/// Flops of a block Cholesky factorisation of the symmetric graph `adjacency` (duplicate
/// and self entries allowed) eliminated in `order` (the vertex at each position), vertex `v`
/// a block of `dim(v)` scalars. A column `d` wide with `r` scalar rows below its diagonal
/// block counts `d·r·(r + d)`: its panel solve and its update of the columns after it.
pub fn elimination_flops(
    adjacency: &[Vec<usize>],
    order: &[usize],
    dim: impl Fn(usize) -> usize,
) -> f64 {
    let n = order.len();
    let mut position = vec![0; n];
    for (k, &v) in order.iter().enumerate() {
        position[v] = k;
    }
    let earlier = |k: usize| {
        adjacency[order[k]]
            .iter()
            .map(|&u| position[u])
            .filter(move |&i| i < k)
    };
    let parent = elimination_tree(n, earlier);
    let mut rows_below = vec![0usize; n];
    visit_factor_rows(&parent, earlier, |j, k| rows_below[j] += dim(order[k]));
    (0..n)
        .map(|k| {
            let (d, r) = (dim(order[k]) as f64, rows_below[k] as f64);
            d * r * (r + d)
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chain(n: usize) -> Vec<Vec<usize>> {
        (0..n)
            .map(|v| {
                let mut out = Vec::new();
                if v > 0 {
                    out.push(v - 1);
                }
                if v + 1 < n {
                    out.push(v + 1);
                }
                out
            })
            .collect()
    }

    #[test]
    fn a_chain_in_order_has_no_fill() {
        // Every column but the last has one block below its diagonal: 3·3·6 flops each.
        let flops = elimination_flops(&chain(5), &[0, 1, 2, 3, 4], |_| 3);
        assert_eq!(flops, 4.0 * 3.0 * 3.0 * 6.0);
    }

    #[test]
    fn a_chain_from_its_middle_fills_in() {
        // Eliminating 2 first joins 1 and 3; then 1 (rows 3 and 0), 3 (rows 0 and 4), 0
        // (row 4): rows below are 2, 2, 2, 1, 0 blocks of one scalar.
        let flops = elimination_flops(&chain(5), &[2, 1, 3, 0, 4], |_| 1);
        assert_eq!(flops, 3.0 * (2.0 * 3.0) + 1.0 * 2.0);
    }

    #[test]
    fn a_star_costs_by_where_its_hub_goes() {
        // Hub 0 joined to 1..=6: last, no fill; first, a clique of six.
        let mut star = vec![(1..7).collect::<Vec<_>>()];
        star.extend((1..7).map(|_| vec![0]));
        let hub_last = elimination_flops(&star, &[1, 2, 3, 4, 5, 6, 0], |_| 2);
        let hub_first = elimination_flops(&star, &[0, 1, 2, 3, 4, 5, 6], |_| 2);
        assert_eq!(hub_last, 6.0 * 2.0 * 2.0 * 4.0);
        // Rows below: 12, 10, 8, 6, 4, 2 scalars, then the last column none.
        let expected: f64 = [12.0, 10.0, 8.0, 6.0, 4.0, 2.0]
            .iter()
            .map(|r| 2.0 * r * (r + 2.0))
            .sum();
        assert_eq!(hub_first, expected);
    }
}
