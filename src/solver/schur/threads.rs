//! The elimination and the back-substitution on more than one thread. The eliminated blocks are
//! cut into contiguous parts of about equal neighbour counts; each part's V⁻¹ is its own slice
//! of the solver's array, so only S (and the reduced right-hand side) is written by
//! every part: the first part into S itself, each other into a private copy that is added to S
//! afterwards, in part order. A part's arithmetic is the one-thread code's; only the order in
//! which the parts' contributions to S are summed differs, so results agree to rounding.

use std::ops::{ControlFlow, Range};
use std::sync::atomic::AtomicBool;

use super::super::budget::Budget;
use super::super::cholesky::NotPositiveDefinite;
use super::super::structure::BlockPattern;
use super::eliminate::{eliminate_blocks, Pass};
use super::reduced::Backend;
use super::{EliminatedBlocks, SchurSolver};

/// What every part reads: the layout of the elimination (see [`SchurSolver`]'s fields).
pub(super) struct View<'a> {
    pub(super) blocks: &'a EliminatedBlocks,
    pub(super) s_block_start: &'a [usize],
    pub(super) s_blocks: &'a [usize],
    pub(super) reduced: &'a BlockPattern,
    /// S's dimension when it is dense (its blocks are then addressed by row and column).
    pub(super) dense_n: Option<usize>,
}

/// What one part writes: its blocks' V⁻¹ (a slice that starts at `v_first` of the solver's
/// array), the W and Y scratch of one block, and S (or the part's copy of it).
pub(super) struct Part<'a> {
    pub(super) v_inverse: &'a mut [f64],
    pub(super) v_first: usize,
    pub(super) w_local: &'a mut [f64],
    pub(super) y_local: &'a mut [f64],
    pub(super) s_values: &'a mut [f64],
}

/// The full system's pattern and values, H, whose W blocks the solve reads.
pub(super) type H<'a> = (&'a BlockPattern, &'a [f64]);

/// Subtracts eliminated blocks' `Y b_e` from a reduced right-hand side.
pub(super) type Reduce = fn(&SchurSolver, H<'_>, Range<usize>, &[f64], &mut [f64]);

/// Back-substitutes eliminated blocks into their rows (a slice that starts at the given row).
pub(super) type BackSubstitute = fn(&SchurSolver, H<'_>, Range<usize>, (&mut [f64], usize), &[f64]);

/// The eliminated blocks `0..eliminated` cut into up to `threads` contiguous parts of about
/// equal neighbour counts (`neighbour_start[e]`: the neighbours before block `e`); one part
/// when there are fewer than 64 blocks per thread.
pub(super) fn parts_by_neighbours(
    neighbour_start: &[usize],
    eliminated: usize,
    threads: usize,
) -> Vec<Range<usize>> {
    let total = neighbour_start[eliminated];
    let mut starts = vec![0];
    if threads > 1 && eliminated >= 64 * threads {
        for k in 1..threads {
            let goal = k * total / threads;
            let at = neighbour_start.partition_point(|&s| s < goal);
            if at > starts[starts.len() - 1] && at < eliminated {
                starts.push(at);
            }
        }
    }
    starts.push(eliminated);
    starts.windows(2).map(|w| w[0]..w[1]).collect()
}

/// `v_inverse` cut into each part's V⁻¹: (its slice, the index its slice starts at).
pub(super) fn v_pieces<'a>(
    parts: &[Range<usize>],
    blocks: &EliminatedBlocks,
    v_inverse: &'a mut [f64],
) -> Vec<(&'a mut [f64], usize)> {
    let mut rest = v_inverse;
    let mut pieces = Vec::with_capacity(parts.len());
    for part in parts {
        let (first, end) = (blocks.v_start[part.start], blocks.v_start[part.end]);
        let (piece, next) = std::mem::take(&mut rest).split_at_mut(end - first);
        rest = next;
        pieces.push((piece, first));
    }
    pieces
}

/// `head` (the eliminated rows) cut into each part's rows: (its blocks, its rows, its first
/// row).
pub(super) fn row_pieces<'a>(
    parts: &[Range<usize>],
    blocks: &EliminatedBlocks,
    head: &'a mut [f64],
) -> Vec<(Range<usize>, &'a mut [f64], usize)> {
    let row = |e: usize| blocks.offset.get(e).copied().unwrap_or(blocks.rows);
    let mut rest = head;
    let mut pieces = Vec::with_capacity(parts.len());
    for blocks in parts {
        let (first, end) = (row(blocks.start), row(blocks.end));
        let (piece, next) = std::mem::take(&mut rest).split_at_mut(end - first);
        rest = next;
        pieces.push((blocks.clone(), piece, first));
    }
    pieces
}

/// A thread other than the caller's: its W and Y scratch and its copies of S and the reduced
/// right-hand side.
#[derive(Debug, Default)]
pub(super) struct Helper {
    w_local: Vec<f64>,
    y_local: Vec<f64>,
    s_values: Vec<f64>,
    rhs: Vec<f64>,
}

impl SchurSolver {
    /// Eliminates and back-substitutes on up to `threads` threads (1: the calling thread);
    /// returns how many it uses: fewer when there are few eliminated blocks.
    pub fn use_threads(&mut self, threads: usize) -> usize {
        self.parts = parts_by_neighbours(&self.blocks.neighbour_start, self.eliminated, threads);
        self.helpers = (1..self.parts.len())
            .map(|_| Helper {
                w_local: vec![0.0; self.w_local.len()],
                y_local: vec![0.0; self.y_local.len()],
                s_values: vec![0.0; self.s_values.len()],
                rhs: vec![0.0; self.rhs.len()],
            })
            .collect();
        self.parts.len()
    }

    /// Every eliminated block into S (which holds U and the shift already), part by part.
    pub(super) fn eliminate_parts(
        &mut self,
        full: &BlockPattern,
        values: &[f64],
        shift: Option<&[f64]>,
        budget: &dyn Budget,
    ) -> Result<ControlFlow<()>, NotPositiveDefinite> {
        let view = View {
            blocks: &self.blocks,
            s_block_start: &self.s_block_start,
            s_blocks: &self.s_blocks,
            reduced: &self.reduced,
            dense_n: match self.backend {
                Backend::Dense { .. } => Some(self.reduced.n),
                Backend::Sparse(_) => None,
            },
        };
        let stop = AtomicBool::new(false);
        let inputs = (full, values, shift);
        let pieces = v_pieces(&self.parts, &self.blocks, &mut self.v_inverse);
        let mut parts = pieces.into_iter().zip(&self.parts);
        let ((first_v, _), first_blocks) = parts.next().expect("one part");
        let results = std::thread::scope(|s| {
            let others: Vec<_> = parts
                .zip(self.helpers.iter_mut())
                .map(|(((v, v_first), blocks), helper)| {
                    let view = &view;
                    let stop = &stop;
                    s.spawn(move || {
                        helper.s_values.fill(0.0);
                        let mut part = Part {
                            v_inverse: v,
                            v_first,
                            w_local: &mut helper.w_local,
                            y_local: &mut helper.y_local,
                            s_values: &mut helper.s_values,
                        };
                        let pass = Pass {
                            blocks: blocks.clone(),
                            inputs,
                            budget: None,
                            stop,
                        };
                        eliminate_blocks(view, &mut part, pass)
                    })
                })
                .collect();
            let mut part = Part {
                v_inverse: first_v,
                v_first: 0,
                w_local: &mut self.w_local,
                y_local: &mut self.y_local,
                s_values: &mut self.s_values,
            };
            let blocks = first_blocks.clone();
            let pass = Pass {
                blocks,
                inputs,
                budget: Some(budget),
                stop: &stop,
            };
            let mine = eliminate_blocks(&view, &mut part, pass);
            crate::solver::parts::mine_then_joined(mine, others)
        });
        for result in results {
            if result?.is_break() {
                return Ok(ControlFlow::Break(()));
            }
        }
        for helper in &self.helpers {
            for (to, from) in self.s_values.iter_mut().zip(&helper.s_values) {
                *to += from;
            }
        }
        Ok(ControlFlow::Continue(()))
    }

    /// The reduced right-hand side `self.rhs −= Σ_e Y_e b_e` over every part (the others into
    /// their copies, added in part order).
    pub(super) fn reduce_parts(&mut self, h: H<'_>, rhs: &[f64], reduce: Reduce) {
        let mut own_rhs = std::mem::take(&mut self.rhs);
        let mut helpers = std::mem::take(&mut self.helpers);
        let this = &*self;
        std::thread::scope(|s| {
            for (blocks, helper) in this.parts[1..].iter().zip(helpers.iter_mut()) {
                s.spawn(move || {
                    helper.rhs.fill(0.0);
                    reduce(this, h, blocks.clone(), rhs, &mut helper.rhs);
                });
            }
            reduce(this, h, this.parts[0].clone(), rhs, &mut own_rhs);
        });
        for helper in &helpers {
            for (to, from) in own_rhs.iter_mut().zip(&helper.rhs) {
                *to += from;
            }
        }
        self.rhs = own_rhs;
        self.helpers = helpers;
    }

    /// Back-substitution over every part: each writes only its own blocks' rows of `head`.
    pub(super) fn back_substitute_parts(
        &self,
        h: H<'_>,
        head: &mut [f64],
        tail: &[f64],
        back: BackSubstitute,
    ) {
        let pieces = row_pieces(&self.parts, &self.blocks, head);
        let mut pieces = pieces.into_iter();
        let (blocks, piece, first) = pieces.next().expect("one part");
        std::thread::scope(|s| {
            for (blocks, piece, first) in pieces {
                s.spawn(move || back(self, h, blocks, (piece, first), tail));
            }
            back(self, h, blocks, (piece, first), tail);
        });
    }
}
