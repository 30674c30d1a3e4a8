//! The linearisation loop over one chunk of the factors (see [`super::split`]), and the driver
//! that runs the chunks: all of them on the calling thread when there is no split, else one per
//! thread with the shared tail summed afterwards.

use std::borrow::Borrow;
use std::ops::{ControlFlow, Range};
use std::sync::atomic::{AtomicBool, Ordering};

use crate::factors::EvaluationError;
use crate::problem::{FactorEntry, Values, Variable};

use super::super::budget::{Budget, FACTORS_PER_CHECK};
use super::super::simd::has_wide_vectors;
use super::super::structure::BlockPattern;
use super::{factor_gram, fixed, Buffers, Scratch, SystemLayout};

/// Where one chunk writes: H's values and b's rows of its own positions, and the shared tail
/// (from position `shared` on); each slice starts at the value index or row given beside it.
struct Target<'a> {
    h_own: (&'a mut [f64], usize),
    h_shared: (&'a mut [f64], usize),
    b_own: (&'a mut [f64], usize),
    b_shared: (&'a mut [f64], usize),
    shared: usize,
}

/// One chunk's inputs that every thread reads.
struct Shared<'a, E> {
    factors: &'a [E],
    values: &'a Values,
    layout: &'a SystemLayout,
    /// Set by the calling thread when its budget stops the linearisation.
    stop: AtomicBool,
}

/// The whole linearisation: on the calling thread, or split as the layout's split says.
pub(super) fn run<E: Borrow<FactorEntry> + Sync, const HESSIAN: bool>(
    factors: &[E],
    values: &Values,
    layout: &SystemLayout,
    scratch: &mut Scratch,
    h: &mut [f64],
    b: &mut [f64],
    budget: &dyn Budget,
) -> Result<ControlFlow<(), f64>, EvaluationError> {
    let common = Shared {
        factors,
        values,
        layout,
        stop: AtomicBool::new(false),
    };
    let split = match &layout.split {
        Some(split) if scratch.helpers.len() + 1 == split.chunks.len() => split,
        _ => {
            let target = Target {
                h_own: (h, 0),
                h_shared: (&mut [], 0),
                b_own: (b, 0),
                b_shared: (&mut [], 0),
                shared: usize::MAX,
            };
            let visits = 0..layout.visit_order.len();
            return chunk::<E, HESSIAN>(&common, &mut scratch.own, visits, target, Some(budget));
        }
    };
    // H and b cut into the chunks' own parts (consecutive) and the shared tail.
    let (mut h_rest, h_tail) = h.split_at_mut(if HESSIAN { split.shared_value_start } else { 0 });
    let (mut b_rest, b_tail) = b.split_at_mut(split.shared_row_start);
    let mut owns = Vec::with_capacity(split.chunks.len());
    for c in &split.chunks {
        let h_len = if HESSIAN { c.values.len() } else { 0 };
        let (h_own, h_next) = std::mem::take(&mut h_rest).split_at_mut(h_len);
        let (b_own, b_next) = std::mem::take(&mut b_rest).split_at_mut(c.rows.len());
        (h_rest, b_rest) = (h_next, b_next);
        owns.push((h_own, b_own));
    }
    let mut owns = owns.into_iter().zip(&split.chunks);
    let (first_own, first_chunk) = owns.next().expect("a split has chunks");
    let results = std::thread::scope(|s| {
        let others: Vec<_> = owns
            .zip(scratch.helpers.iter_mut())
            .map(|(((h_own, b_own), c), helper)| {
                let common = &common;
                s.spawn(move || {
                    let target = Target {
                        h_own: (h_own, c.values.start),
                        h_shared: (
                            if HESSIAN { &mut helper.h[..] } else { &mut [] },
                            split.shared_value_start,
                        ),
                        b_own: (b_own, c.rows.start),
                        b_shared: (&mut helper.b[..], split.shared_row_start),
                        shared: split.shared,
                    };
                    chunk::<E, HESSIAN>(common, &mut helper.buffers, c.visits.clone(), target, None)
                })
            })
            .collect();
        let target = Target {
            h_own: (first_own.0, first_chunk.values.start),
            h_shared: (h_tail, split.shared_value_start),
            b_own: (first_own.1, first_chunk.rows.start),
            b_shared: (b_tail, split.shared_row_start),
            shared: split.shared,
        };
        let visits = first_chunk.visits.clone();
        let mine = chunk::<E, HESSIAN>(&common, &mut scratch.own, visits, target, Some(budget));
        crate::solver::parts::mine_then_joined(mine, others)
    });
    let total = match crate::solver::parts::sum_of_parts(results)? {
        ControlFlow::Continue(total) => total,
        ControlFlow::Break(()) => return Ok(ControlFlow::Break(())),
    };
    // The other threads' parts of the shared tail, in chunk order.
    for helper in &scratch.helpers {
        if HESSIAN {
            for (to, from) in h[split.shared_value_start..].iter_mut().zip(&helper.h) {
                *to += from;
            }
        }
        for (to, from) in b[split.shared_row_start..].iter_mut().zip(&helper.b) {
            *to += from;
        }
    }
    Ok(ControlFlow::Continue(total))
}

/// One chunk's factors into `target` (zeroed first); the calling thread's chunk checks `budget`
/// and tells the others through `common.stop`, which they read as often.
fn chunk<E: Borrow<FactorEntry>, const HESSIAN: bool>(
    common: &Shared<'_, E>,
    buffers: &mut Buffers,
    visits: Range<usize>,
    target: Target<'_>,
    budget: Option<&dyn Budget>,
) -> Result<ControlFlow<(), f64>, EvaluationError> {
    if has_wide_vectors() {
        // SAFETY: the CPU has the features `chunk_wide` is compiled for.
        unsafe { chunk_wide::<E, HESSIAN>(common, buffers, visits, target, budget) }
    } else {
        chunk_with::<E, HESSIAN>(common, buffers, visits, target, budget)
    }
}

#[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2,fma"))]
fn chunk_wide<E: Borrow<FactorEntry>, const HESSIAN: bool>(
    common: &Shared<'_, E>,
    buffers: &mut Buffers,
    visits: Range<usize>,
    target: Target<'_>,
    budget: Option<&dyn Budget>,
) -> Result<ControlFlow<(), f64>, EvaluationError> {
    chunk_with::<E, HESSIAN>(common, buffers, visits, target, budget)
}

/// The linearisation loop over one chunk; without `HESSIAN` it fills only b (H's slices may be
/// empty).
// The per-factor loop linearisation time is spent in; its parts are inlined into it.
#[inline(always)]
fn chunk_with<E: Borrow<FactorEntry>, const HESSIAN: bool>(
    common: &Shared<'_, E>,
    buffers: &mut Buffers,
    visits: Range<usize>,
    target: Target<'_>,
    budget: Option<&dyn Budget>,
) -> Result<ControlFlow<(), f64>, EvaluationError> {
    let Target {
        h_own,
        h_shared,
        b_own,
        b_shared,
        shared,
    } = target;
    for part in [
        &mut *h_own.0,
        &mut *h_shared.0,
        &mut *b_own.0,
        &mut *b_shared.0,
    ] {
        part.fill(0.0);
    }
    let (layout, values) = (common.layout, common.values);
    let pattern = &layout.pattern;
    let mut total = 0.0;
    let mut refs: Vec<&dyn Variable> = Vec::with_capacity(8);
    let mut col_offsets = [0usize; 16];
    for (k, &f) in layout.visit_order[visits].iter().enumerate() {
        if k % FACTORS_PER_CHECK == FACTORS_PER_CHECK - 1 && stopped(common, budget) {
            return Ok(ControlFlow::Break(()));
        }
        let entry = common.factors[f].borrow();
        let vars = entry.variables();
        refs.clear();
        refs.extend(vars.iter().map(|&v| values.variable(v)));
        let d = entry.factor.residual_dim();
        let mut cols = 0;
        for (k, r) in refs.iter().enumerate() {
            col_offsets[k] = cols;
            cols += r.tangent_dim();
        }
        total += factor_gram::<HESSIAN>(entry, &refs, d, cols, buffers)?;
        let (gram, gradient) = (&buffers.gram[..cols * cols], &buffers.gradient[..cols]);
        for (li, &v) in vars.iter().enumerate() {
            if let Some(p) = layout.position_of_var[v] {
                let (o, c0, dim) = (pattern.offset[p], col_offsets[li], pattern.dim[p]);
                let (to, first) = if p >= shared {
                    (&mut *b_shared.0, b_shared.1)
                } else {
                    (&mut *b_own.0, b_own.1)
                };
                let rows = &mut to[o - first..o - first + dim];
                fixed::add_scaled_exact(rows, &gradient[c0..c0 + dim], -1.0);
            }
        }
        if !HESSIAN {
            continue;
        }
        for &(li, lj, pair) in &layout.slots[layout.slot_start[f]..layout.slot_start[f + 1]] {
            let (vi, vj) = (vars[li as usize], vars[lj as usize]);
            let (a, bpos) = (
                layout.position_of_var[vi].unwrap_or(0),
                layout.position_of_var[vj].unwrap_or(0),
            );
            let diagonal = a == bpos;
            let (ci, cj) = (col_offsets[li as usize], col_offsets[lj as usize]);
            let (da, db) = (pattern.dim[a], pattern.dim[bpos]);
            let (h, first) = if bpos >= shared {
                (&mut *h_shared.0, h_shared.1)
            } else {
                (&mut *h_own.0, h_own.1)
            };
            let args = (pattern, pair, diagonal, gram, cols, ci, cj);
            match (da, db) {
                (3, 3) => scatter::<3, 3>(h, first, args),
                (6, 6) => scatter::<6, 6>(h, first, args),
                (9, 9) => scatter::<9, 9>(h, first, args),
                (9, 3) => scatter::<9, 3>(h, first, args),
                _ => scatter_any(h, first, args, (da, db)),
            }
        }
    }
    Ok(ControlFlow::Continue(total))
}

/// What a scatter of one gram block into H reads: H's pattern, the block's pair and whether it
/// is diagonal, the factor's gram and its column count, and the block's columns in the gram.
type ScatterArgs<'a> = (
    &'a BlockPattern,
    usize,
    bool,
    &'a [f64],
    usize,
    usize,
    usize,
);

/// Whether the chunks stop here: the calling thread's chunk asks `budget` and tells the others
/// through `common.stop`; the others read it.
#[inline(always)]
fn stopped<E: Borrow<FactorEntry>>(common: &Shared<'_, E>, budget: Option<&dyn Budget>) -> bool {
    match budget {
        Some(budget) => {
            let stop = budget.checkpoint().is_break();
            if stop {
                common.stop.store(true, Ordering::Relaxed);
            }
            stop
        }
        None => common.stop.load(Ordering::Relaxed),
    }
}

/// The `da × db` block of the gram at columns (`ci`, `cj`) added into H, for block sizes the
/// fixed kernels do not cover.
#[inline(always)]
fn scatter_any(
    h: &mut [f64],
    first: usize,
    (pattern, pair, diagonal, gram, cols, ci, cj): ScatterArgs<'_>,
    (da, db): (usize, usize),
) {
    for q in 0..db {
        let rows = if diagonal { q } else { 0 };
        let base = pattern.value_index(pair, diagonal, rows, q) - first;
        // Column cj + q of the symmetric gram is its row: contiguous over rr.
        let source = &gram[(cj + q) * cols + ci + rows..(cj + q) * cols + ci + da];
        for (hv, g) in h[base..base + da - rows].iter_mut().zip(source) {
            *hv += g;
        }
    }
}

/// [`fixed::scatter_block`] with the arguments the loop passes through unchanged.
#[inline(always)]
fn scatter<const R: usize, const C: usize>(
    h: &mut [f64],
    first: usize,
    (pattern, pair, diagonal, gram, cols, ci, cj): ScatterArgs<'_>,
) {
    fixed::scatter_block::<R, C>(pattern, h, first, pair, diagonal, gram, cols, ci, cj);
}
