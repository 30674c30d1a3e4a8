//! `factord ba`'s iteration lines and summary in Ceres' layout, so that numbers can be read side
//! by side with a Ceres run: cost = ½Σρ(‖r‖²) (our χ² halved), `cost_change`, `tr_ratio` (the
//! gain ratio), `tr_radius` (Levenberg-Marquardt's 1/λ, as Ceres reports its LM radius), and the
//! printf field widths of Ceres' `LoggingCallback` and `Summary::FullReport`.
//!
//! One difference remains, said in docs/guide/jobs-and-cli.md: `|gradient|` is the gradient at the point the
//! iteration started from, where Ceres shows it at the point it ended at.

use std::time::Instant;

use factord::solver::{IterationReport, Method, SolverOptions, Summary};

pub const HEADER: &str = "iter      cost      cost_change  |gradient|   |step|    tr_ratio  tr_radius  ls_iter  iter_time  total_time";

/// C's `% .Ne`: a space or a minus sign, N decimals, and an exponent of at least two digits
/// (`4.185660e+06`), where Rust's `{:e}` writes `4.18566e6`.
pub fn c_exponent(value: f64, decimals: usize) -> String {
    let sign = if value.is_sign_negative() && !value.is_nan() {
        '-'
    } else {
        ' '
    };
    if !value.is_finite() {
        return format!("{sign}{}", if value.is_nan() { "nan" } else { "inf" });
    }
    let text = format!("{:.decimals$e}", value.abs());
    let (mantissa, exponent) = text.split_once('e').expect("{:e} writes an exponent");
    let exponent: i32 = exponent.parse().expect("{:e} writes an integer exponent");
    let exponent_sign = if exponent < 0 { '-' } else { '+' };
    format!("{sign}{mantissa}e{exponent_sign}{:02}", exponent.abs())
}

/// Turns the solver's per-iteration reports into Ceres' rows, keeping the times between them.
pub struct CeresRows {
    method: Method,
    start: Instant,
    last: Instant,
    /// χ² of the current point (before the next iteration's step).
    chi2: f64,
    initial_radius: f64,
    started: bool,
}

impl CeresRows {
    /// `initial_chi2`: χ² of the starting point (the first row's cost).
    pub fn new(options: &SolverOptions, initial_chi2: f64) -> Self {
        let initial_radius = match options.method {
            Method::LevenbergMarquardt if options.damp_first_step => 1.0 / options.initial_lambda,
            Method::Dogleg => options.initial_trust_radius,
            // Undamped: no trust region (an infinite radius).
            _ => f64::INFINITY,
        };
        let now = Instant::now();
        Self {
            method: options.method,
            start: now,
            last: now,
            chi2: initial_chi2,
            initial_radius,
            started: false,
        }
    }

    /// The rows for `report`: before the first, the header and row 0 (the starting point, whose
    /// gradient the first report carries).
    pub fn rows(&mut self, report: &IterationReport) -> String {
        let now = Instant::now();
        let mut out = String::new();
        if !self.started {
            self.started = true;
            out.push_str(HEADER);
            out.push('\n');
            out.push_str(&row(
                0,
                self.chi2 / 2.0,
                0.0,
                report.gradient_max_norm,
                0.0,
                0.0,
                self.initial_radius,
                0,
                0.0,
                0.0,
            ));
        }
        let radius = match self.method {
            Method::LevenbergMarquardt => report.lambda.map_or(f64::INFINITY, |l| 1.0 / l),
            Method::Dogleg => report.trust_radius.unwrap_or(f64::INFINITY),
            Method::GaussNewton => f64::INFINITY,
        };
        out.push_str(&row(
            report.iteration,
            report.chi2 / 2.0,
            (self.chi2 - report.trial_chi2) / 2.0,
            report.gradient_max_norm,
            report.step_two_norm,
            report.gain_ratio,
            radius,
            // A direct factorisation: one linear solve per step, as Ceres counts it.
            1,
            (now - self.last).as_secs_f64(),
            (now - self.start).as_secs_f64(),
        ));
        self.chi2 = report.chi2;
        self.last = now;
        out
    }
}

#[allow(clippy::too_many_arguments)] // one argument per Ceres column, in its order
fn row(
    iteration: usize,
    cost: f64,
    cost_change: f64,
    gradient: f64,
    step: f64,
    ratio: f64,
    radius: f64,
    linear_iterations: usize,
    iteration_seconds: f64,
    total_seconds: f64,
) -> String {
    // Ceres: "% 4d % 8e   % 3.2e   % 3.2e  % 3.2e  % 3.2e % 3.2e     % 4d   % 3.2e   % 3.2e"
    format!(
        "{:>4} {}   {}   {}  {}  {} {}     {:>4}   {}   {}\n",
        iteration,
        c_exponent(cost, 6),
        c_exponent(cost_change, 2),
        c_exponent(gradient, 2),
        c_exponent(step, 2),
        c_exponent(ratio, 2),
        c_exponent(radius, 2),
        linear_iterations,
        c_exponent(iteration_seconds, 2),
        c_exponent(total_seconds, 2),
    )
}

/// The cost, step and time blocks of Ceres' FullReport, from our Summary (cost = χ²/2).
pub fn summary_report(summary: &Summary) -> String {
    let t = &summary.timings;
    let (initial, last) = (summary.initial_chi2 / 2.0, summary.final_chi2 / 2.0);
    let minimizer = t.initialization_seconds
        + t.linearize_seconds
        + t.factorize_seconds
        + t.linear_solve_seconds
        + t.evaluate_seconds;
    let termination = if summary.converged {
        "CONVERGENCE"
    } else {
        "NO_CONVERGENCE"
    };
    format!(
        "\nCost:\nInitial        {:>30}\nFinal          {:>30}\nChange         {:>30}\n\
         \nMinimizer iterations         {:>16}\nSuccessful steps               {:>14}\nUnsuccessful steps             {:>14}\n\
         \nTime (in seconds):\nPreprocessor        {:>25.6}\n\
         \n  Residual only evaluation {:>18.6}\n  Jacobian & residual evaluation {:>12.6}\n  Linear solver       {:>23.6}\nMinimizer           {:>25.6}\n\
         \nTotal               {:>25.6}\n\nTermination:        {:>25} ({})\n",
        c_exponent(initial, 6),
        c_exponent(last, 6),
        c_exponent(initial - last, 6),
        summary.iterations,
        summary.successful_steps,
        summary.unsuccessful_steps,
        t.preprocess_seconds,
        t.evaluate_seconds,
        t.linearize_seconds,
        t.factorize_seconds + t.linear_solve_seconds,
        minimizer,
        summary.solve_seconds,
        termination,
        summary.termination.message,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exponents_are_written_as_c_printf_writes_them() {
        assert_eq!(c_exponent(4185660.0, 6), " 4.185660e+06");
        assert_eq!(c_exponent(-0.000123, 2), "-1.23e-04");
        assert_eq!(c_exponent(0.0, 2), " 0.00e+00");
        assert_eq!(c_exponent(1e100, 2), " 1.00e+100");
        assert_eq!(c_exponent(f64::INFINITY, 2), " inf");
    }

    #[test]
    fn a_row_has_ceres_column_layout() {
        let line = row(
            1, 1.06259e5, 4.08e6, 8.99e6, 5.36e2, 9.82e-1, 3e4, 1, 0.165, 0.503,
        );
        assert_eq!(
            line,
            "   1  1.062590e+05    4.08e+06    8.99e+06   5.36e+02   9.82e-01  3.00e+04        1    1.65e-01    5.03e-01\n"
        );
    }
}
