//! Running the `factord` binary in tests: the command, and the two outcomes most tests expect.

use std::process::{Command, Output};

pub fn factord() -> Command {
    Command::new(env!("CARGO_BIN_EXE_factord"))
}

pub trait Run {
    /// Runs it and asserts it succeeded (its stderr in the failure); its output.
    fn succeeds(&mut self) -> Output;
    /// Runs it and asserts it exited with 2, the code for bad input; its stderr.
    fn refused(&mut self) -> String;
}

impl Run for Command {
    fn succeeds(&mut self) -> Output {
        let output = self.output().expect("factord runs");
        assert!(
            output.status.success(),
            "{}",
            String::from_utf8_lossy(&output.stderr)
        );
        output
    }

    fn refused(&mut self) -> String {
        let output = self.output().expect("factord runs");
        assert_eq!(
            output.status.code(),
            Some(2),
            "{}",
            String::from_utf8_lossy(&output.stderr)
        );
        String::from_utf8_lossy(&output.stderr).into_owned()
    }
}
