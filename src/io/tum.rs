//! TUM trajectories: `timestamp tx ty tz qx qy qz qw` per line (w last); 2D poses are written in
//! the z = 0 plane with a yaw quaternion. Numbers are in shortest round-trip form (Rust's `{}`).
//!
//! Pose graphs carry no time, so the first column is either the vertex id ([`to_string`], and
//! [`to_string_with_ids`] which says so in a header) or a stamp from a separate `id stamp` file
//! ([`parse_stamps`], [`to_string_with_stamps`]).

use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::Path;

use nalgebra::{UnitQuaternion, Vector3};

use super::{lines, parse_error, IoError, PoseGraph};
use crate::geometry::{Se2, Se3};
use crate::problem::Key;

/// The header of a trajectory whose first column is the vertex id: evo and other TUM readers
/// skip `#` lines, and a person reading the file learns the column is not a time.
pub const VERTEX_ID_HEADER: &str =
    "# vertex_id tx ty tz qx qy qz qw (first column: the pose graph's vertex id, not a timestamp)\n";
pub const TIMESTAMP_HEADER: &str = "# timestamp tx ty tz qx qy qz qw\n";

/// Stamps by vertex id, each kept as written in its file so that no digit is lost (a
/// nanosecond Unix time has more digits than an f64 holds).
pub type Stamps = HashMap<Key, String>;

/// The trajectory, first column the vertex id, without a header.
pub fn to_string(graph: &PoseGraph) -> String {
    poses(graph, |key| Ok(key.to_string())).expect("ids are always there")
}

/// [`to_string`] after [`VERTEX_ID_HEADER`].
pub fn to_string_with_ids(graph: &PoseGraph) -> String {
    format!("{VERTEX_ID_HEADER}{}", to_string(graph))
}

/// The trajectory with each vertex's stamp from `stamps` (read from `stamps_file`, named in the
/// error when a pose has none).
pub fn to_string_with_stamps(
    graph: &PoseGraph,
    stamps: &Stamps,
    stamps_file: &Path,
) -> Result<String, IoError> {
    let body = poses(graph, |key| {
        stamps.get(&key).cloned().ok_or_else(|| IoError::Invalid {
            file: stamps_file.to_path_buf(),
            reason: format!("no stamp for vertex {key}"),
        })
    })?;
    Ok(format!("{TIMESTAMP_HEADER}{body}"))
}

fn poses(
    graph: &PoseGraph,
    mut first_column: impl FnMut(Key) -> Result<String, IoError>,
) -> Result<String, IoError> {
    let mut out = String::new();
    for &key in &graph.vertex_order {
        let values = &graph.problem.values;
        let (t, q) = if let Some(p) = values.get_as::<Se2>(key) {
            (
                Vector3::new(p.x, p.y, 0.0),
                UnitQuaternion::from_euler_angles(0.0, 0.0, p.theta),
            )
        } else if let Some(p) = values.get_as::<Se3>(key) {
            (p.translation, p.rotation)
        } else {
            continue;
        };
        push_line(
            &mut out,
            first_column(key)?,
            [t.x, t.y, t.z],
            [q.i, q.j, q.k, q.w],
        );
    }
    Ok(out)
}

/// Appends one trajectory line, `first_column tx ty tz qx qy qz qw`, numbers in shortest
/// round-trip form (every digit the value has, none it does not).
pub fn push_line(
    out: &mut String,
    first_column: impl std::fmt::Display,
    [x, y, z]: [f64; 3],
    [qx, qy, qz, qw]: [f64; 4],
) {
    let _ = writeln!(out, "{first_column} {x} {y} {z} {qx} {qy} {qz} {qw}");
}

/// Reads `id stamp` lines (`#` comments and blank lines skipped); `path` names the file in errors.
/// Extra fields after the stamp are refused rather than guessed at.
pub fn parse_stamps(path: &Path, text: &str) -> Result<Stamps, IoError> {
    let mut stamps = Stamps::new();
    for line in lines(text) {
        let [id, stamp] = line.tokens[..] else {
            return Err(parse_error(
                path,
                line.number,
                format!("expected `id stamp`, found {} fields", line.tokens.len()),
            ));
        };
        let key: Key = id
            .parse()
            .map_err(|_| parse_error(path, line.number, format!("`{id}` is not a vertex id")))?;
        if !stamp.parse::<f64>().is_ok_and(f64::is_finite) {
            return Err(parse_error(
                path,
                line.number,
                format!("`{stamp}` is not a finite number"),
            ));
        }
        if stamps.insert(key, stamp.to_string()).is_some() {
            return Err(parse_error(
                path,
                line.number,
                format!("a second stamp for vertex {key}"),
            ));
        }
    }
    Ok(stamps)
}

pub fn write(graph: &PoseGraph, path: &Path) -> Result<(), IoError> {
    std::fs::write(path, to_string(graph)).map_err(|source| IoError::Write {
        file: path.to_path_buf(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stamps_keep_their_digits_and_bad_lines_name_the_line() {
        let path = Path::new("stamps.txt");
        let stamps = parse_stamps(path, "# id stamp\n0 1403715273.262142944\n1 2.5\n").unwrap();
        assert_eq!(stamps[&0], "1403715273.262142944");
        let e = parse_stamps(path, "0 1\n1 x\n").unwrap_err().to_string();
        assert!(e.contains("stamps.txt:2:") && e.contains("`x`"), "{e}");
        let e = parse_stamps(path, "0 1\n0 2\n").unwrap_err().to_string();
        assert!(e.contains("second stamp for vertex 0"), "{e}");
        let e = parse_stamps(path, "0 1 2\n").unwrap_err().to_string();
        assert!(e.contains("expected `id stamp`"), "{e}");
    }
}
