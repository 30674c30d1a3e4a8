//! Ordering the whole factor again once its fill has outgrown the order it was given.
//!
//! An update orders only the part it eliminates again, with its new variables last; the rest
//! keeps the order it had. Over a long stream that order drifts far from what a fresh one of
//! the whole graph gives: every loop closure hangs the paths it refactors under the newest
//! pose, and the columns it does not reach keep the fill of an order chosen for a smaller map.
//! The 300 000-pose generated city stream reached 23 GB at pose 283 840 (the fresh order's
//! factor of the whole graph holds 140 M scalars, about 1.1 GB), and the 100 000-pose one
//! held 128 scalars per column against 47 for a fresh order.
//!
//! So when the factor holds [`REORDER_GROWTH`] times the scalars it held right after it was
//! last ordered whole, the next update eliminates every column again in a fresh order (the
//! same AMD / nested-dissection choice as any refactored part, the update's new variables
//! last). Its cost is one batch factorisation; since the fill must double between two of
//! them, their cost summed over a stream stays within a small multiple of the last one's,
//! as with a growing vector. The factor's memory stays within that multiple of a fresh
//! order's, whatever the stream.

use super::IncrementalEngine;

/// The factor is ordered whole again once it holds this many times the scalars it held
/// right after its last whole order.
const REORDER_GROWTH: usize = 2;
/// Below this many scalar nonzeros (8 MB) the factor is small enough that its order does not
/// matter.
const REORDER_FROM_NNZ: usize = 1 << 20;

impl IncrementalEngine {
    /// Whether the factor's fill has outgrown its last whole order (see the module comment).
    pub(super) fn fill_outgrew_its_order(&self) -> bool {
        let nnz = self.factor.nnz();
        let from = self.whole_order_from.unwrap_or(REORDER_FROM_NNZ);
        nnz >= from && nnz > REORDER_GROWTH * self.whole_order_nnz
    }

    /// Orders the whole factor again only from `nnz` scalar nonzeros on (tests reach it with
    /// small graphs; the default is [`REORDER_FROM_NNZ`]).
    pub fn order_whole_from(&mut self, nnz: usize) {
        self.whole_order_from = Some(nnz);
    }

    /// Adds every free variable to `touched`, so that the pass eliminates the whole factor
    /// again.
    pub(super) fn touch_every_column(&self, touched: &mut Vec<usize>) {
        touched.extend((0..self.theta.len()).filter(|&v| self.free[v]));
    }
}
