//! The implicit Schur complement on more than one thread. The eliminated blocks are cut into
//! parts as the explicit solver cuts them (`threads::parts_by_neighbours`); every pass over
//! them runs one part per thread:
//! - the "factorisation": each part's V⁻¹ is its own slice of the solver's array; the
//!   preconditioner's blocks are written by every part, the first into the preconditioner
//!   itself, each other into a private copy added afterwards in part order;
//! - each product `S x` (the most time of an implicit solve: one per CG iteration) and the
//!   reduction of the right-hand side: the first part into the output, the others into private
//!   vectors of the reduced size, added in part order;
//! - the back-substitution: each part writes only its own blocks' rows.
//!
//! A part's arithmetic is the one-thread code's; only the order in which the parts' sums are
//! added differs, so results agree to rounding.

use std::ops::{ControlFlow, Range};
use std::sync::atomic::AtomicBool;

use super::super::budget::Budget;
use super::super::cholesky::NotPositiveDefinite;
use super::threads::{parts_by_neighbours, row_pieces, v_pieces, H};
use super::ImplicitSchur;
use crate::solver::parts::mine_then_joined;

/// A thread other than the caller's: its copy of the preconditioner's blocks and a vector of
/// the reduced size (a product's or a reduction's part).
#[derive(Debug, Default)]
pub(super) struct Helper {
    jacobi: Vec<f64>,
    reduced: Vec<f64>,
}

impl ImplicitSchur {
    /// Factorises and solves on up to `threads` threads (1: the calling thread); returns how
    /// many it uses: fewer when there are few eliminated blocks.
    pub fn use_threads(&mut self, threads: usize) -> usize {
        self.parts = parts_by_neighbours(&self.blocks.neighbour_start, self.eliminated, threads);
        self.helpers = (1..self.parts.len())
            .map(|_| Helper {
                jacobi: vec![0.0; self.jacobi.len()],
                reduced: vec![0.0; self.shift.len()],
            })
            .collect();
        self.parts.len()
    }

    /// Every eliminated block's V⁻¹ and its part of the preconditioner (which holds U's
    /// diagonal blocks and the shift already), part by part; the calling thread's part checks
    /// `budget`.
    pub(super) fn eliminate_parts(
        &mut self,
        h: H<'_>,
        shift: Option<&[f64]>,
        budget: &dyn Budget,
    ) -> Result<ControlFlow<()>, NotPositiveDefinite> {
        let mut v_inverse = std::mem::take(&mut self.v_inverse);
        let mut jacobi = self.jacobi.take_blocks();
        let mut helpers = std::mem::take(&mut self.helpers);
        let stop = AtomicBool::new(false);
        let this = &*self;
        let mut v_pieces = v_pieces(&this.parts, &this.blocks, &mut v_inverse).into_iter();
        let (first_v, _) = v_pieces.next().expect("one part");
        let results = std::thread::scope(|s| {
            let others: Vec<_> = this.parts[1..]
                .iter()
                .zip(v_pieces)
                .zip(helpers.iter_mut())
                .map(|((blocks, (v, _)), helper)| {
                    let stop = &stop;
                    s.spawn(move || {
                        helper.jacobi.fill(0.0);
                        let numeric = (v, &mut helper.jacobi[..]);
                        this.eliminate_range(blocks.clone(), numeric, (h, shift), None, stop)
                    })
                })
                .collect();
            let numeric = (first_v, &mut jacobi[..]);
            let blocks = this.parts[0].clone();
            let mine = this.eliminate_range(blocks, numeric, (h, shift), Some(budget), &stop);
            mine_then_joined(mine, others)
        });
        for helper in &helpers {
            for (to, from) in jacobi.iter_mut().zip(&helper.jacobi) {
                *to += from;
            }
        }
        self.v_inverse = v_inverse;
        self.jacobi.restore(jacobi);
        self.helpers = helpers;
        for result in results {
            if result?.is_break() {
                return Ok(ControlFlow::Break(()));
            }
        }
        Ok(ControlFlow::Continue(()))
    }

    /// y = S x = (U + D) x − W V⁻¹ Wᵀ x, the eliminated blocks part by part (on the calling
    /// thread alone when `helpers` are not one per part beside the first).
    pub(super) fn product_parts(&self, h: H<'_>, x: &[f64], y: &mut [f64], helpers: &mut [Helper]) {
        self.reduced_product(h, x, y);
        self.over_parts(y, helpers, |blocks, out| {
            self.eliminated_products(blocks, h, x, out)
        });
    }

    /// `reduced −= Σ_e W_e V_e⁻¹ b_e` (`b`: the eliminated rows), part by part.
    pub(super) fn reduce_parts(
        &self,
        h: H<'_>,
        b: &[f64],
        reduced: &mut [f64],
        helpers: &mut [Helper],
    ) {
        self.over_parts(reduced, helpers, |blocks, out| {
            self.reduce_range(blocks, h, b, out)
        });
    }

    /// Runs `pass(blocks, out)` for every part: the first on the calling thread into `out`,
    /// the others into their helpers' zeroed vectors, which are then added to `out` in part
    /// order. All on the calling thread when `helpers` do not match the parts.
    fn over_parts(
        &self,
        out: &mut [f64],
        helpers: &mut [Helper],
        pass: impl Fn(Range<usize>, &mut [f64]) + Sync,
    ) {
        if helpers.len() + 1 != self.parts.len() {
            pass(0..self.eliminated, out);
            return;
        }
        let pass = &pass;
        std::thread::scope(|s| {
            for (blocks, helper) in self.parts[1..].iter().zip(helpers.iter_mut()) {
                s.spawn(move || {
                    helper.reduced.fill(0.0);
                    pass(blocks.clone(), &mut helper.reduced);
                });
            }
            pass(self.parts[0].clone(), out);
        });
        for helper in helpers.iter() {
            for (to, from) in out.iter_mut().zip(&helper.reduced) {
                *to += from;
            }
        }
    }

    /// The eliminated rows `head` back-substituted from the reduced `solution`, part by part
    /// (each part writes only its own rows).
    pub(super) fn back_substitute_parts(&self, h: H<'_>, head: &mut [f64], solution: &[f64]) {
        let pieces = row_pieces(&self.parts, &self.blocks, head);
        std::thread::scope(|s| {
            let mut pieces = pieces.into_iter();
            let (blocks, rows, first) = pieces.next().expect("one part");
            for (blocks, rows, first) in pieces {
                s.spawn(move || self.back_substitute_range(blocks, h, (rows, first), solution));
            }
            self.back_substitute_range(blocks, h, (rows, first), solution);
        });
    }
}
