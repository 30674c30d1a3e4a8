//! GTSAM's 2D text format with landmarks (`victoria_park.txt`), as GTSAM's `load2D` reads it:
//!
//! ```text
//! ODOMETRY i j dx dy dθ c1 c2 c3 c4 c5 c6     relative pose, noise as below
//! LANDMARK i l x y v1 v2 v3                   landmark l seen from pose i at body-frame (x, y)
//! ```
//!
//! - The odometry's six numbers follow GTSAM's automatic layout: `a 0 0 b 0 c` is a covariance
//!   `xx xy xθ yy yθ θθ`, `a 0 b c 0 0` TORO's information `xx xy yy θθ xθ yθ` (`toro.rs`).
//! - A sighting becomes a bearing-range factor: bearing `atan2(y, x)`, range `√(x² + y²)`, with
//!   σ_bearing = √(v1/10) and σ_range = √v1 when |v1 − v3| < 1e-4, else σ = 1 for both.
//! - Landmark `l` is the key `('l' << 56) | l` (GTSAM's `Symbol('l', l)`), poses keep their ids.
//! - There are no vertices: poses start from the chained odometry and each landmark from its
//!   first sighting (the spanning tree of `edges.rs`, rooted at the smallest pose id).

use std::path::Path;

use nalgebra::DMatrix;

use super::edges::{add_edges, Edge};
use super::toro::edge_information;
use super::{id, lines, numbers, parse_error, Dimension, IoError, PoseGraph};
use crate::factors::{BearingRangeSe2, BetweenSe2};
use crate::geometry::Se2;
use crate::problem::{Key, Problem};

/// The key of landmark `l`: GTSAM's `Symbol('l', l)`.
pub fn landmark_key(l: Key) -> Key {
    (u64::from(b'l') << 56) | l
}

/// Whether `text` is in this format (its first record is `ODOMETRY` or `LANDMARK`).
pub fn detect(first_tag: &str) -> bool {
    matches!(first_tag, "ODOMETRY" | "LANDMARK")
}

pub fn parse(path: &Path, text: &str) -> Result<PoseGraph, IoError> {
    let mut edges = Vec::new();
    for line in lines(text) {
        let tag = line.tokens[0];
        match tag {
            "ODOMETRY" => {
                let f = numbers(path, &line, 11)?;
                let (i, j) = (
                    id(path, line.number, f[0], 1)?,
                    id(path, line.number, f[1], 2)?,
                );
                let information = edge_information(&f[5..]).ok_or_else(|| {
                    parse_error(path, line.number, "the covariance is not invertible")
                })?;
                edges.push(Edge {
                    factor: Box::new(BetweenSe2::new(i, j, Se2::new(f[2], f[3], f[4]))),
                    information,
                    label: format!("ODOMETRY {i} {j} ({}:{})", path.display(), line.number),
                    path,
                    line: line.number,
                });
            }
            "LANDMARK" => {
                let f = numbers(path, &line, 7)?;
                let i = id(path, line.number, f[0], 1)?;
                let l = id(path, line.number, f[1], 2)?;
                if l >= 1 << 56 {
                    return Err(parse_error(path, line.number, "landmark id beyond 2^56"));
                }
                if f[2] == 0.0 && f[3] == 0.0 {
                    return Err(parse_error(
                        path,
                        line.number,
                        "a landmark at the pose itself has no bearing",
                    ));
                }
                let (v1, v3) = (f[4], f[6]);
                let (sigma_bearing, sigma_range) = if (v1 - v3).abs() < 1e-4 && v1 > 0.0 {
                    ((v1 / 10.0).sqrt(), v1.sqrt())
                } else {
                    (1.0, 1.0)
                };
                let information = DMatrix::from_diagonal(&nalgebra::DVector::from_row_slice(&[
                    1.0 / (sigma_bearing * sigma_bearing),
                    1.0 / (sigma_range * sigma_range),
                ]));
                edges.push(Edge {
                    factor: Box::new(BearingRangeSe2::from_body_position(
                        i,
                        landmark_key(l),
                        f[2],
                        f[3],
                    )),
                    information,
                    label: format!("LANDMARK {i} {l} ({}:{})", path.display(), line.number),
                    path,
                    line: line.number,
                });
            }
            other => {
                return Err(parse_error(
                    path,
                    line.number,
                    format!("unknown record `{other}` in a GTSAM text file (ODOMETRY, LANDMARK)"),
                ))
            }
        }
    }
    if edges.is_empty() {
        return Err(IoError::Invalid {
            file: path.to_path_buf(),
            reason: "no vertices or edges".into(),
        });
    }
    let mut problem = Problem::new();
    let order = add_edges(&mut problem, edges, Box::new(Se2::identity()), path)?;
    Ok(PoseGraph {
        problem,
        dimension: Dimension::Two,
        vertex_order: order,
    })
}
