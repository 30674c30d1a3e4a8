//! Progress on a terminal for file loads and solves (indicatif), drawn on stderr and only when
//! stderr is a terminal: piped or redirected runs, and `--quiet`, print no progress at all.

use std::io::IsTerminal;
use std::path::Path;
use std::time::Duration;

use indicatif::{ProgressBar, ProgressStyle};

use factord::solver::IterationReport;

pub struct Progress {
    bar: ProgressBar,
}

fn visible(quiet: bool) -> bool {
    !quiet && std::io::stderr().is_terminal()
}

impl Progress {
    /// A spinner while `path` is read and parsed (files load whole; there is no byte count to
    /// show until parsing is done).
    pub fn loading(path: &Path, quiet: bool) -> Self {
        if !visible(quiet) {
            return Self {
                bar: ProgressBar::hidden(),
            };
        }
        let bar = ProgressBar::new_spinner().with_message(format!("loading {}", path.display()));
        bar.set_style(
            ProgressStyle::with_template("{spinner} {msg} [{elapsed}]").expect("valid template"),
        );
        bar.tick(); // drawn now, not after the first tick: most loads take milliseconds
        bar.enable_steady_tick(Duration::from_millis(100));
        Self { bar }
    }

    /// A bar over the iteration budget, with the current cost.
    pub fn solving(max_iterations: usize, quiet: bool) -> Self {
        if !visible(quiet) {
            return Self {
                bar: ProgressBar::hidden(),
            };
        }
        let bar = ProgressBar::new(max_iterations as u64);
        bar.set_style(
            ProgressStyle::with_template(
                "solving [{bar:30}] iteration {pos}/{len} {msg} [{elapsed}]",
            )
            .expect("valid template")
            .progress_chars("=> "),
        );
        bar.enable_steady_tick(Duration::from_millis(200));
        Self { bar }
    }

    pub fn iteration(&self, report: &IterationReport) {
        self.bar.set_position(report.iteration as u64);
        self.bar.set_message(format!("chi2 {:.6e}", report.chi2));
    }

    /// Runs `print` (which writes to stdout) with the bar out of the way.
    pub fn suspend(&self, print: impl FnOnce()) {
        self.bar.suspend(print)
    }

    pub fn finish(self) {
        self.bar.finish_and_clear();
    }
}
