//! Reading and writing pose graphs: g2o (2D/3D), TORO / course `.dat` pairs, TUM trajectories.
//!
//! Files are parsed whole into records first (every malformed line is reported with file, line
//! number and reason), then vertices are added before edges, so record order does not matter.
//!
//! Layer 5: imports `geometry`, `factors`, `problem` and `solver`.

pub mod bal;
pub mod direct_ba;
mod edges;
pub mod euroc;
pub mod g2o;
pub mod gtsam_text;
pub mod ply;
pub mod svg;
pub mod toro;
pub mod tum;

use std::path::{Path, PathBuf};

use crate::problem::{Key, Problem, ProblemError};

#[derive(Debug, thiserror::Error)]
pub enum IoError {
    #[error("{file}: cannot read: {source}")]
    Read {
        file: PathBuf,
        source: std::io::Error,
    },
    #[error("{file}: cannot write: {source}")]
    Write {
        file: PathBuf,
        source: std::io::Error,
    },
    #[error("{file}:{line}: {reason}")]
    Parse {
        file: PathBuf,
        line: usize,
        reason: String,
    },
    #[error("{file}: {reason}")]
    Invalid { file: PathBuf, reason: String },
}

/// Pose dimension of a loaded graph.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dimension {
    Two,
    Three,
}

/// A loaded pose graph: the problem plus what is needed to write it back.
#[derive(Debug)]
pub struct PoseGraph {
    pub problem: Problem,
    pub dimension: Dimension,
    /// Vertex keys in file order, for writing.
    pub vertex_order: Vec<Key>,
}

/// One parsed record: its line number and its whitespace-separated tokens.
pub(crate) struct Line<'a> {
    pub number: usize,
    pub tokens: Vec<&'a str>,
}

pub(crate) fn read_text(path: &Path) -> Result<String, IoError> {
    std::fs::read_to_string(path).map_err(|source| IoError::Read {
        file: path.to_path_buf(),
        source,
    })
}

/// `text` without a leading UTF-8 byte-order mark, which editors on Windows write and which is
/// no part of the first record.
pub(crate) fn without_bom(text: &str) -> &str {
    text.strip_prefix('\u{feff}').unwrap_or(text)
}

pub(crate) fn lines(text: &str) -> impl Iterator<Item = Line<'_>> {
    without_bom(text).lines().enumerate().filter_map(|(i, l)| {
        let l = l.trim();
        (!l.is_empty() && !l.starts_with('#')).then(|| Line {
            number: i + 1,
            tokens: l.split_whitespace().collect(),
        })
    })
}

/// Parses the numeric fields of `line`, expecting exactly `count` after the tag.
pub(crate) fn numbers(path: &Path, line: &Line, count: usize) -> Result<Vec<f64>, IoError> {
    let fields = &line.tokens[1..];
    if fields.len() != count {
        return Err(parse_error(
            path,
            line.number,
            format!(
                "{} expects {count} fields, found {}",
                line.tokens[0],
                fields.len()
            ),
        ));
    }
    fields
        .iter()
        .enumerate()
        .map(|(k, t)| match t.parse::<f64>() {
            Ok(v) if v.is_finite() => Ok(v),
            Ok(_) => Err(parse_error(
                path,
                line.number,
                format!("field {} (`{t}`) is not finite", k + 1),
            )),
            Err(_) => Err(parse_error(
                path,
                line.number,
                format!("field {} (`{t}`) is not a number", k + 1),
            )),
        })
        .collect()
}

/// The id in field `field` (1-based) of `line`, read as an exact 64-bit integer: GTSAM's symbol
/// keys (`('x' << 56) | i`, a robot's or a landmark's) are beyond f64's integers. A field written
/// as a float (`3.0`) is read as [`id`] reads numbers.
pub(crate) fn key_field(path: &Path, line: &Line, field: usize) -> Result<Key, IoError> {
    let token = line.tokens[field];
    token
        .parse::<Key>()
        .ok()
        .or_else(|| {
            let value = token.parse::<f64>().ok()?;
            id(path, line.number, value, field).ok()
        })
        .ok_or_else(|| {
            parse_error(
                path,
                line.number,
                format!("field {field} (`{token}`) is not a valid id"),
            )
        })
}

/// A vertex or edge id: a non-negative integer.
/// `line` is the 1-based line number, for the error.
pub(crate) fn id(path: &Path, line: usize, value: f64, field: usize) -> Result<Key, IoError> {
    if value < 0.0 || value.fract() != 0.0 || value > 2f64.powi(53) {
        return Err(parse_error(
            path,
            line,
            format!("field {field} (`{value}`) is not a valid id"),
        ));
    }
    Ok(value as Key)
}

pub(crate) fn parse_error(path: &Path, line: usize, reason: impl Into<String>) -> IoError {
    IoError::Parse {
        file: path.to_path_buf(),
        line,
        reason: reason.into(),
    }
}

pub(crate) fn problem_error(path: &Path, line: usize, e: ProblemError) -> IoError {
    parse_error(path, line, e.to_string())
}

/// Graph file formats.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    G2o,
    Toro,
    /// GTSAM's text format with landmarks (`ODOMETRY`, `LANDMARK`).
    Gtsam,
}

impl Format {
    pub fn parse(name: &str) -> Option<Self> {
        match name {
            "g2o" => Some(Self::G2o),
            "toro" => Some(Self::Toro),
            "gtsam" => Some(Self::Gtsam),
            _ => None,
        }
    }
}

/// Parses a whole graph held in memory (`name` labels errors), in `format` or, when `None`,
/// detected as [`load`] does.
pub fn parse_text(text: &str, name: &Path, format: Option<Format>) -> Result<PoseGraph, IoError> {
    let format = format.unwrap_or_else(|| detect(text));
    match format {
        Format::Toro => toro::parse(&[(name, text)]),
        Format::G2o => g2o::parse(&[(name, text)]),
        Format::Gtsam => gtsam_text::parse(name, text),
    }
}

/// The format of `text` by its first record: TORO, GTSAM's landmark text, else g2o.
fn detect(text: &str) -> Format {
    match lines(text).next() {
        Some(l) if gtsam_text::detect(l.tokens[0]) => Format::Gtsam,
        _ if is_toro(text) => Format::Toro,
        _ => Format::G2o,
    }
}

fn is_toro(text: &str) -> bool {
    lines(text)
        .next()
        .is_some_and(|l| matches!(l.tokens[0], "VERTEX2" | "EDGE2" | "VERTEX" | "EDGE"))
}

/// Loads a pose graph, choosing the reader by content: `VERTEX2`/`EDGE2` records are TORO (with
/// an optional separate edges file, as the course's `-v.dat`/`-e.dat` pairs), anything else g2o.
pub fn load(path: &Path, edges: Option<&Path>) -> Result<PoseGraph, IoError> {
    let text = read_text(path)?;
    let edge_text = edges.map(read_text).transpose()?;
    parse_pair((path, &text), edges.zip(edge_text.as_deref()))
}

/// [`load`] for texts already read (a file from standard input, say): `graph` and the optional
/// separate `edges` are each a name for errors and the text.
pub fn parse_pair(
    graph: (&Path, &str),
    edges: Option<(&Path, &str)>,
) -> Result<PoseGraph, IoError> {
    let (path, text) = graph;
    match edges {
        Some((edges_path, edge_text)) => {
            if is_toro(text)
                || lines(edge_text)
                    .next()
                    .is_some_and(|l| l.tokens[0] == "EDGE2")
            {
                toro::parse(&[(path, text), (edges_path, edge_text)])
            } else {
                g2o::parse(&[(path, text), (edges_path, edge_text)])
            }
        }
        None => parse_text(text, path, None),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const BOM: &str = "\u{feff}";

    #[test]
    fn a_leading_byte_order_mark_is_skipped_by_every_text_reader() {
        let name = Path::new("bom");
        let g2o = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n";
        let toro = "VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\nEDGE2 0 1 1 0 0 1 0 1 1 0 0\n";
        for (text, format) in [(g2o, Format::G2o), (toro, Format::Toro)] {
            let with_bom = format!("{BOM}{text}");
            let graph = parse_text(&with_bom, name, None).expect("a BOM is skipped");
            assert_eq!(graph.vertex_order, [0, 1], "{format:?}");
            assert!(
                parse_text(&with_bom, name, Some(format)).is_ok(),
                "{format:?}"
            );
        }
        let bal = "1 1 1\n0 0 1.0 2.0\n0 0 0 0 0 0 500 0 0\n0 0 5\n";
        let problem = bal::parse(name, &format!("{BOM}{bal}")).expect("a BOM is skipped");
        assert_eq!((problem.num_cameras, problem.num_points), (1, 1));
        let stamps = format!("{BOM}0 1.5\n");
        assert!(tum::parse_stamps(name, &stamps).is_ok());
        // Only at the start: anywhere else it is no whitespace and stays an error.
        assert!(parse_text(
            &format!("VERTEX_SE2 0 0 0 0\n{BOM}VERTEX_SE2 1 1 0 0\n"),
            name,
            None
        )
        .is_err());
    }
}
