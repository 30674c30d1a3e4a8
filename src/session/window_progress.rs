//! What a window session reports about its solves: the counters and last summary that a graph
//! session keeps in its state, kept here for the window, which is solved at every keyframe
//! outside the session lock. Without them a window session's stats said sequence 0, no
//! variables, no factors and no solves, and `/summary` answered 404, while its page drew the
//! whole trajectory.

use crate::api::wire::SessionStats;
use crate::fusion::gauss_newton::WindowUpdate;
use crate::fusion::window::SlidingWindow;
use crate::solver::summary::{non_negative_chi2, Timings, UsedOptions};
use crate::solver::{Summary, Termination, TerminationReason};

/// A window session's counters. Locked after the window (never the other way round) and
/// never while taking the session lock.
#[derive(Default)]
pub(super) struct WindowProgress {
    /// Fusion batches the window took (all their messages, or those before a rejected one):
    /// what a graph session's batch sequence is, replayed alike from the journal.
    sequence: u64,
    /// The sequence the last window solve reflects.
    solved_sequence: u64,
    solves: u64,
    /// The window's problem as the last batch left it (marginalised keyframes have left it).
    variables: usize,
    factors: usize,
    chi2: Option<f64>,
    converged: bool,
    last_summary: Option<Summary>,
}

impl WindowProgress {
    /// A batch the window took (`applied` > 0 of its messages), with the window it left.
    pub(super) fn record_batch(&mut self, window: Option<&SlidingWindow>) {
        self.sequence += 1;
        if let Some(w) = window {
            self.variables = w.problem().values.len();
            self.factors = w.problem().factors().len();
        }
    }

    /// A window solve within the batch being applied (which is `sequence + 1` once recorded).
    pub(super) fn record_solve(
        &mut self,
        window: &SlidingWindow,
        update: &WindowUpdate,
        seconds: f64,
    ) {
        self.solves += 1;
        self.solved_sequence = self.sequence + 1;
        self.chi2 = Some(non_negative_chi2(update.chi2));
        self.converged = update.converged;
        self.last_summary = Some(summary(window, update, seconds));
    }

    /// `stats` with the window's numbers where a graph session's would be.
    pub(super) fn fill(&self, stats: &mut SessionStats) {
        stats.sequence = self.sequence;
        stats.solved_sequence = self.solved_sequence;
        stats.num_variables = self.variables;
        stats.num_factors = self.factors;
        stats.solves = self.solves;
        stats.chi2 = self.chi2;
        stats.converged = self.converged || self.solves == 0;
        stats.last_summary = self.last_summary.clone();
    }
}

/// The window solve as a [`Summary`]: its Gauss-Newton steps and χ², with the window's
/// problem as the update left it (its oldest keyframes marginalised).
fn summary(window: &SlidingWindow, update: &WindowUpdate, seconds: f64) -> Summary {
    let problem = window.problem();
    let values = &problem.values;
    let free: Vec<usize> = (0..values.len()).filter(|&v| !values.is_fixed(v)).collect();
    let options = window.options.solver.clone();
    let factors = problem.factors();
    let reason = if update.converged {
        TerminationReason::FunctionTolerance
    } else {
        TerminationReason::MaxIterations
    };
    Summary {
        method: options.method.name().into(),
        used: UsedOptions {
            method: format!("sliding window ({} path)", update.path),
            linear_solver: if update.path == "window" {
                "envelope Cholesky of the window's keyframes".into()
            } else {
                "the general solver's".into()
            },
            factorization: if update.path == "window" {
                "envelope".into()
            } else {
                "sparse".into()
            },
            ordering: if update.path == "window" {
                "keyframes in time order".into()
            } else {
                "the general solver's".into()
            },
            threads: 1,
            initialization: "none (the window's last estimate, new keyframe predicted)".into(),
            gauge_fixed: Vec::new(),
            schur: None,
            region_variables: None,
            incremental: None,
        },
        given_options: options,
        num_variables: values.len(),
        num_free_variables: free.len(),
        num_factors: factors.len(),
        num_residuals: factors.iter().map(|f| f.factor.residual_dim()).sum(),
        num_parameters: free.iter().map(|&v| values.variable(v).tangent_dim()).sum(),
        jacobian_nnz_blocks: factors.iter().map(|f| f.factor.keys().len()).sum(),
        hessian_nnz: 0,
        factor_nnz: 0,
        initial_chi2: non_negative_chi2(update.initial_chi2),
        initialized_chi2: None,
        final_chi2: non_negative_chi2(update.chi2),
        iterations: update.iterations,
        successful_steps: update.iterations,
        unsuccessful_steps: 0,
        termination: Termination {
            reason,
            value: update.chi2,
            threshold: 0.0,
            message: if update.converged {
                format!("window update converged in {} step(s)", update.iterations)
            } else {
                format!(
                    "window update stopped after {} step(s); the rest is left to the next keyframe",
                    update.iterations
                )
            },
        },
        converged: update.converged,
        solve_seconds: seconds,
        timings: Timings::default(),
        iteration_log: Vec::new(),
    }
}
