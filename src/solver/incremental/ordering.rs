//! The elimination order of the part of the factor an update eliminates again.
//!
//! Its graph is what the affected variables share: the factors among them, and, for every
//! untouched column that reaches them, the clique of its affected rows (the fill that subtree
//! left on them, iSAM2's cached factors of orphaned subtrees). AMD orders that graph, and the
//! variables of the update's new factors are then moved last (in AMD's relative order): the
//! constraint of CCOLAMD that iSAM2 applies, so the newest poses become the root and the next
//! update (odometry from the newest pose) refactors a column or two, while a loop closure
//! refactors a path to the root, not the map.

use crate::solver::structure::BlockOrdering;

/// `affected` in the order to eliminate them. `neighbours(v, out)` lists the affected
/// variables sharing a factor with `v`; `cliques` are groups of affected variables that fill
/// in together; `last[v]` marks the variables to eliminate last.
pub fn order_affected(
    affected: &[usize],
    mut neighbours: impl FnMut(usize, &mut Vec<usize>),
    cliques: &[Vec<usize>],
    last: &[bool],
    local: &mut [u32],
) -> Vec<usize> {
    for (i, &v) in affected.iter().enumerate() {
        local[v] = i as u32;
    }
    let mut adjacency: Vec<Vec<usize>> = vec![Vec::new(); affected.len()];
    let mut out = Vec::new();
    for (i, &v) in affected.iter().enumerate() {
        out.clear();
        neighbours(v, &mut out);
        adjacency[i].extend(out.iter().map(|&u| local[u] as usize));
    }
    for clique in cliques {
        for &a in clique {
            for &b in clique {
                if a != b {
                    adjacency[local[a] as usize].push(local[b] as usize);
                }
            }
        }
    }
    let ordering = BlockOrdering::amd(adjacency);
    let in_amd_order = ordering.block_at.iter().map(|&i| affected[i]);
    let (mut order, constrained): (Vec<usize>, Vec<usize>) = in_amd_order.partition(|&v| !last[v]);
    order.extend(constrained);
    order
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constrained_variables_come_last_and_everything_once() {
        // A chain 0-1-2-3-4 with 0 and 4 marked last.
        let affected = [0, 1, 2, 3, 4];
        let mut last = vec![false; 5];
        last[0] = true;
        last[4] = true;
        let mut local = vec![0; 5];
        let order = order_affected(
            &affected,
            |v, out| {
                if v > 0 {
                    out.push(v - 1);
                }
                if v < 4 {
                    out.push(v + 1);
                }
            },
            &[vec![1, 3]],
            &last,
            &mut local,
        );
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, vec![0, 1, 2, 3, 4]);
        assert!(order[3..].contains(&0) && order[3..].contains(&4));
    }
}
