//! How linearisation shares its factors between threads without locks: the factors, in visit
//! order, are cut into contiguous chunks at changes of their first elimination position, and
//! each chunk writes H's columns and b's rows of its own positions directly. Positions from
//! `shared` on (in bundle adjustment: the cameras, which every chunk's observations touch) are
//! written by every chunk: the first into H and b themselves, the others into private copies of
//! that tail which are added afterwards, in chunk order.
//!
//! This needs every position a chunk touches below `shared` to be its own, which holds when the
//! factors of a chunk only reach, besides their own positions, positions at or after `shared`:
//! points eliminated first and cameras last. `shared` is the smallest position some chunk
//! reaches outside its own range; a split whose shared tail is most of H is not made (a pose
//! graph's chain reaches forward everywhere), and linearisation then stays on one thread.

use std::borrow::Borrow;
use std::ops::Range;

use crate::problem::FactorEntry;

use super::SystemLayout;

/// The shared tail may hold at most this fraction of H's values: the other threads zero and add
/// their copies of it on every linearisation.
const MAX_SHARED_FRACTION: f64 = 0.25;

/// One thread's part of a linearisation.
#[derive(Debug, Clone)]
pub(in crate::solver) struct Chunk {
    /// Its factors: a range of the layout's visit order.
    pub(super) visits: Range<usize>,
    /// H's values (indices) and b's rows it alone writes: the columns and rows of its positions.
    pub(super) values: Range<usize>,
    pub(super) rows: Range<usize>,
}

/// The chunks of a multi-threaded linearisation; see the module documentation.
#[derive(Debug, Clone)]
pub(in crate::solver) struct Split {
    pub(super) chunks: Vec<Chunk>,
    /// First position that more than one chunk writes; its column's first value and its first
    /// row. Everything from there on is the shared tail.
    pub(super) shared: usize,
    pub(super) shared_value_start: usize,
    pub(super) shared_row_start: usize,
}

impl Split {
    /// Values of H in the shared tail.
    pub(super) fn shared_values(&self, nnz: usize) -> usize {
        nnz - self.shared_value_start
    }

    pub(super) fn shared_rows(&self, n: usize) -> usize {
        n - self.shared_row_start
    }
}

/// Cuts `layout`'s factors into at most `threads` chunks as described in the module
/// documentation; `None` when fewer than two chunks come out or the shared tail is too large.
pub(super) fn split<E: Borrow<FactorEntry>>(
    factors: &[E],
    layout: &SystemLayout,
    threads: usize,
) -> Option<Split> {
    let pattern = &layout.pattern;
    let nb = pattern.dim.len();
    let visits = layout.visit_order.len();
    if threads < 2 || visits < 2 * threads {
        return None;
    }
    let positions = |f: usize| {
        factors[f]
            .borrow()
            .variables()
            .iter()
            .filter_map(|&v| layout.position_of_var[v])
    };
    let first: Vec<usize> = layout
        .visit_order
        .iter()
        .map(|&f| positions(f).min().unwrap_or(nb))
        .collect();
    // Chunk starts in the visit order: about equal factor counts, moved to the next change of
    // first position so that a position's factors stay together.
    let mut starts = vec![0];
    for k in 1..threads {
        let mut at = (k * visits / threads).max(starts[starts.len() - 1] + 1);
        while at < visits && first[at] == first[at - 1] {
            at += 1;
        }
        if at >= visits || first[at] >= nb {
            break;
        }
        starts.push(at);
    }
    if starts.len() < 2 {
        return None;
    }
    let own_from: Vec<usize> = (0..starts.len())
        .map(|k| if k == 0 { 0 } else { first[starts[k]] })
        .collect();
    let mut shared = nb;
    for k in 0..starts.len() - 1 {
        let end = own_from[k + 1];
        for &f in &layout.visit_order[starts[k]..starts[k + 1]] {
            for q in positions(f) {
                if q >= end {
                    shared = shared.min(q);
                }
            }
        }
    }
    if shared <= own_from[own_from.len() - 1] {
        return None;
    }
    let value_start = |p: usize| {
        if p >= nb {
            pattern.nnz()
        } else {
            pattern.col_ptr[pattern.offset[p]]
        }
    };
    let row_start = |p: usize| {
        if p >= nb {
            pattern.n
        } else {
            pattern.offset[p]
        }
    };
    let shared_value_start = value_start(shared);
    if (pattern.nnz() - shared_value_start) as f64 > MAX_SHARED_FRACTION * pattern.nnz() as f64 {
        return None;
    }
    let chunks = (0..starts.len())
        .map(|k| {
            let (from, to) = (own_from[k], own_from.get(k + 1).copied().unwrap_or(shared));
            Chunk {
                visits: starts[k]..starts.get(k + 1).copied().unwrap_or(visits),
                values: value_start(from)..value_start(to),
                rows: row_start(from)..row_start(to),
            }
        })
        .collect();
    Some(Split {
        chunks,
        shared,
        shared_value_start,
        shared_row_start: row_start(shared),
    })
}
