//! Union-find over indices, for the connected components of a factor graph (the gauge
//! anchoring of a batch solve, and the fusion window's anchored components).

/// The root of `x`'s set in the forest `parent` (a root is its own parent), halving the path on
/// the way so later queries are shorter.
pub fn find_root(parent: &mut [usize], mut x: usize) -> usize {
    while parent[x] != x {
        parent[x] = parent[parent[x]];
        x = parent[x];
    }
    x
}
