//! File arguments where `-` stands for standard input or standard output, as in Unix tools. When
//! a command writes data to standard output, its progress lines and summaries go to standard
//! error instead ([`Console`]), so `factord solve in.g2o --out - > out.g2o` holds only the graph.

use std::convert::Infallible;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::str::FromStr;

use super::data_dir;
use super::CliError;

/// The name standard input goes by in error messages (`<stdin>:3: …`).
pub const STDIN_NAME: &str = "<stdin>";

#[derive(Clone, Debug)]
pub enum InputArg {
    Stdin,
    File(PathBuf),
}

impl FromStr for InputArg {
    type Err = Infallible;
    fn from_str(s: &str) -> Result<Self, Infallible> {
        Ok(if s == "-" {
            Self::Stdin
        } else {
            Self::File(PathBuf::from(s))
        })
    }
}

impl InputArg {
    /// The name parse errors carry: the file as found, or `<stdin>`.
    pub fn name(&self) -> PathBuf {
        match self {
            Self::Stdin => PathBuf::from(STDIN_NAME),
            Self::File(path) => data_dir::resolve(path),
        }
    }

    /// The whole text; `argument` (e.g. `--edges`) names the argument in errors.
    pub fn read_to_string(&self, argument: &str) -> Result<String, CliError> {
        let read_error = |path: &Path, source: std::io::Error| {
            let hint = match (self, source.kind()) {
                (Self::File(_), std::io::ErrorKind::NotFound) => data_dir::not_found_hint(path),
                _ => String::new(),
            };
            CliError::Read {
                argument: argument.to_string(),
                path: path.to_path_buf(),
                source,
                hint,
            }
        };
        match self {
            Self::Stdin => {
                let mut text = String::new();
                std::io::stdin()
                    .lock()
                    .read_to_string(&mut text)
                    .map_err(|e| read_error(Path::new(STDIN_NAME), e))?;
                Ok(text)
            }
            Self::File(path) => {
                std::fs::read_to_string(data_dir::resolve(path)).map_err(|e| read_error(path, e))
            }
        }
    }
}

/// Refuses two arguments that both read standard input: the first would take it all.
pub fn one_stdin(inputs: &[(&str, Option<&InputArg>)]) -> Result<(), CliError> {
    let takers = inputs
        .iter()
        .filter(|(_, i)| matches!(i, Some(InputArg::Stdin)));
    at_most_one(takers.map(|(name, _)| *name), "standard input")
}

/// The second of the arguments set to `-` for `stream`, if any, refused naming the first.
fn at_most_one<'a>(
    mut takers: impl Iterator<Item = &'a str>,
    stream: &str,
) -> Result<(), CliError> {
    match (takers.next(), takers.next()) {
        (Some(first), Some(second)) => Err(CliError::Argument {
            argument: second.to_string(),
            reason: format!("`-` ({stream}) is already taken by {first}; give a file"),
        }),
        _ => Ok(()),
    }
}

#[derive(Clone, Debug)]
pub enum OutputArg {
    Stdout,
    File(PathBuf),
}

impl FromStr for OutputArg {
    type Err = Infallible;
    fn from_str(s: &str) -> Result<Self, Infallible> {
        Ok(if s == "-" {
            Self::Stdout
        } else {
            Self::File(PathBuf::from(s))
        })
    }
}

impl OutputArg {
    pub fn is_stdout(&self) -> bool {
        matches!(self, Self::Stdout)
    }

    /// The file's path, or `None` for standard output.
    pub fn path(&self) -> Option<&Path> {
        match self {
            Self::Stdout => None,
            Self::File(path) => Some(path),
        }
    }

    /// Writes `bytes` whole; `argument` (e.g. `--out`) names the argument in errors.
    pub fn write(&self, argument: &str, bytes: &[u8]) -> Result<(), CliError> {
        let (path, result) = match self {
            Self::Stdout => {
                let mut out = std::io::stdout().lock();
                (
                    PathBuf::from("<stdout>"),
                    out.write_all(bytes).and_then(|()| out.flush()),
                )
            }
            Self::File(path) => (path.clone(), std::fs::write(path, bytes)),
        };
        result.map_err(|source| CliError::Write {
            argument: argument.to_string(),
            path,
            source,
        })
    }
}

/// Refuses two arguments that both write standard output: their data would be interleaved.
pub fn one_stdout(outputs: &[(&str, Option<&OutputArg>)]) -> Result<(), CliError> {
    let takers = outputs
        .iter()
        .filter(|(_, o)| o.is_some_and(OutputArg::is_stdout));
    at_most_one(takers.map(|(name, _)| *name), "standard output")
}

/// Where a command's human-readable lines go: standard output, unless data goes there.
#[derive(Clone, Copy)]
pub struct Console {
    to_stderr: bool,
    quiet: bool,
}

impl Console {
    /// `data_on_stdout`: some output argument is `-`. `quiet`: print nothing.
    pub fn new(data_on_stdout: bool, quiet: bool) -> Self {
        Self {
            to_stderr: data_on_stdout,
            quiet,
        }
    }

    /// The console of a command writing `outputs`: at most one of them may be `-` (refused
    /// naming the second), and when one is, the console prints to standard error.
    pub fn for_outputs(
        outputs: &[(&str, Option<&OutputArg>)],
        quiet: bool,
    ) -> Result<Self, CliError> {
        one_stdout(outputs)?;
        let data_on_stdout = outputs
            .iter()
            .any(|(_, o)| o.is_some_and(OutputArg::is_stdout));
        Ok(Self::new(data_on_stdout, quiet))
    }

    pub fn quiet(&self) -> bool {
        self.quiet
    }

    /// Prints `text` as is (callers end their lines).
    pub fn print(&self, text: &str) {
        if self.quiet {
            return;
        }
        if self.to_stderr {
            eprint!("{text}");
        } else {
            print!("{text}");
        }
    }
}
