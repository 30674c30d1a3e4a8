//! What a caller lets one solve spend beyond its options: when to stop (a deadline, a
//! cancellation), when to give its CPU to others (preemption), and how much memory it may use.
//!
//! The solver calls [`Budget::checkpoint`] between small pieces of work (a few thousand factors
//! of a linearisation, each factorisation, each phase of the initialisation), so a solve stops or
//! yields within milliseconds, not at the end of an iteration that may take a minute. A
//! checkpoint may block: the caller can hand its worker to others there and resume later with
//! every buffer of the solve intact. A numeric factorisation is one call into faer and cannot be
//! split, so its cost is predicted from the symbolic factorisation (see [`FactorCost`]) and it is
//! not started when it would overrun the time left.

use std::ops::ControlFlow;
use std::time::Duration;

use super::linear::LinearSolver;
use super::linearize::SystemLayout;
use super::options::{Initialization, SolverOptions};
use crate::problem::Problem;

/// Bounds on one solve, given by its caller. The solver only reads them.
pub trait Budget {
    /// `Break`: stop now; the solve answers with the last accepted estimate and an
    /// `interrupted` termination. May block while the caller lets other work run.
    fn checkpoint(&self) -> ControlFlow<()>;

    /// Time left before the solve must stop (`None`: no limit).
    fn remaining(&self) -> Option<Duration> {
        None
    }

    /// Bytes the solve may use (`None`: no limit); a solve estimated above it is refused with
    /// [`super::SolverError::MemoryLimit`] before any numeric work.
    fn max_memory_bytes(&self) -> Option<u64> {
        None
    }
}

/// No limits: the library's and the CLI's solves.
pub struct Unlimited;

impl Budget for Unlimited {
    fn checkpoint(&self) -> ControlFlow<()> {
        ControlFlow::Continue(())
    }
}

/// Linearisation and evaluation check the budget every this many factors. Few enough that a
/// chunk of the costliest user-defined factors (a few ms each to linearise) stays near a tenth
/// of a second; a check is an atomic load and a clock read, well under 1 % of even 64 of the
/// cheapest factors.
pub const FACTORS_PER_CHECK: usize = 64;

/// Floating-point operations a numeric factorisation will take, known from its symbolic
/// analysis, and the rate the last one ran at, to predict the next one's time.
#[derive(Debug, Clone, Copy)]
pub struct FactorCost {
    pub flops: f64,
    /// Measured flop rate of this solve's last factorisation (`None` before the first).
    pub measured_rate: Option<f64>,
}

/// Assumed flop rate before a solve has measured its own: a single-threaded faer factorisation
/// ran at 8–20 GFLOP/s on the machines we measured; assuming the fast end means a first
/// factorisation is predicted short rather than refused for nothing, and later ones use the
/// measured rate.
const ASSUMED_FLOPS_PER_SECOND: f64 = 2.0e10;

impl FactorCost {
    pub fn predicted(&self) -> Duration {
        let rate = self.measured_rate.unwrap_or(ASSUMED_FLOPS_PER_SECOND);
        Duration::from_secs_f64(self.flops / rate.max(1.0))
    }

    /// Whether a factorisation of this cost fits in what `budget` has left.
    pub fn fits(&self, budget: &dyn Budget) -> bool {
        budget
            .remaining()
            .is_none_or(|left| self.predicted() <= left)
    }

    /// Records how long a factorisation of this cost took.
    pub fn measure(&mut self, took: Duration) {
        let seconds = took.as_secs_f64();
        if seconds > 1e-3 && self.flops > 0.0 {
            self.measured_rate = Some(self.flops / seconds);
        }
    }
}

/// Bytes a solve will hold at its peak, from the graph's size and the symbolic factorisation:
/// the problem, a trial copy of the values, the normal equations (pattern indices, H, a damped
/// copy, block maps), the factor with faer's workspaces, and the chordal initialisation's
/// system. That system has one block per variable of at most half its dimension (2D: 1 of 3,
/// 3D: 3 of 6), so its factor is at most a quarter of the main one. Measured peaks were 0.8-1.4x
/// this estimate (100k-pose Manhattan graph: 0.5 GB; 60k poses in a 40 m box: 2.6 GB).
pub fn estimate_memory(
    problem: &Problem,
    layout: &SystemLayout,
    chol: &LinearSolver,
    options: &SolverOptions,
) -> u64 {
    // A boxed variable with its key and index entries, and a factor with its boxed measurement,
    // keys, square-root information and layout slots.
    const VARIABLE_BYTES: u64 = 160;
    const FACTOR_BYTES: u64 = 320;
    let variables = problem.values.len() as u64;
    let graph = variables * 2 * VARIABLE_BYTES + problem.factors().len() as u64 * FACTOR_BYTES;
    let nnz = layout.pattern.nnz() as u64;
    // H's values, its scalar row indices unless forgotten (a Schur solve), and the damped copy
    // a sparse Cholesky factorises (the Schur complement shifts in place).
    let copies =
        1 + u64::from(layout.pattern.has_scalar_rows()) + u64::from(!chol.shifts_in_place());
    let system = 8 * (copies * nnz + 8 * layout.n() as u64);
    let factor = chol.numeric_bytes();
    let initialization = if options.initialization == Initialization::None {
        0
    } else {
        factor / 4
    };
    graph + system + factor + initialization
}
