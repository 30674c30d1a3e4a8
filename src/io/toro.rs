//! TORO `.graph` files and the course's `.dat` pairs: `VERTEX2 id x y θ` and
//! `EDGE2 i j dx dy dθ I_xx I_xy I_yy I_tt I_xt I_yt` — information in TORO order
//! (xx xy yy tt xt yt), not g2o's. `EQUIV` (TORO's node merge directive) is ignored.
//!
//! GTSAM's text files use the same `EDGE2` record with a *covariance* in the order
//! `xx xy xθ yy yθ θθ` (e.g. `w20000.txt`: `3.16228 0 0 3.16228 0 5`); GTSAM's loader tells the
//! two apart by the pattern of zeros. Six numbers `a 0 0 b 0 c` (a, b, c ≠ 0) are read as that
//! covariance, as GTSAM reads them: as TORO information they would give `yy = 0`, which is never
//! valid, so no TORO file is read differently. Files without vertices get them from a spanning
//! tree of the edges (`edges.rs`).

use std::path::Path;

use nalgebra::DMatrix;

use super::edges::{add_edges, Edge};
use super::{id, lines, numbers, parse_error, problem_error, Dimension, IoError, PoseGraph};
use crate::factors::BetweenSe2;
use crate::geometry::Se2;
use crate::problem::Problem;

/// Ω from the six TORO fields `xx xy yy tt xt yt`.
pub fn information_from_toro(f: &[f64]) -> DMatrix<f64> {
    let (xx, xy, yy, tt, xt, yt) = (f[0], f[1], f[2], f[3], f[4], f[5]);
    DMatrix::from_row_slice(3, 3, &[xx, xy, xt, xy, yy, yt, xt, yt, tt])
}

/// The six numbers' pattern that GTSAM's loader reads as a covariance `xx xy xθ yy yθ θθ`.
fn is_gtsam_covariance(f: &[f64]) -> bool {
    f[0] != 0.0 && f[1] == 0.0 && f[2] == 0.0 && f[3] != 0.0 && f[4] == 0.0 && f[5] != 0.0
}

/// Ω of an `EDGE2` record's six numbers (module doc); `None` for a GTSAM covariance that is
/// not invertible.
pub(super) fn edge_information(f: &[f64]) -> Option<DMatrix<f64>> {
    if is_gtsam_covariance(f) {
        let covariance = DMatrix::from_row_slice(
            3,
            3,
            &[f[0], f[1], f[2], f[1], f[3], f[4], f[2], f[4], f[5]],
        );
        covariance.try_inverse()
    } else {
        Some(information_from_toro(f))
    }
}

pub fn parse(files: &[(&Path, &str)]) -> Result<PoseGraph, IoError> {
    let mut problem = Problem::new();
    let mut order = Vec::new();
    let mut edges = Vec::new();
    for &(path, text) in files {
        for line in lines(text) {
            match line.tokens[0] {
                "VERTEX2" | "VERTEX" => {
                    let f = numbers(path, &line, 4)?;
                    let key = id(path, line.number, f[0], 1)?;
                    problem
                        .add_variable(key, Box::new(Se2::new(f[1], f[2], f[3])))
                        .map_err(|e| problem_error(path, line.number, e))?;
                    order.push(key);
                }
                "EDGE2" | "EDGE" => {
                    edges.push((path, line.number, numbers(path, &line, 11)?, line.tokens[0]))
                }
                "EQUIV" => {}
                other => {
                    return Err(parse_error(
                        path,
                        line.number,
                        format!("unknown record `{other}` in a TORO file"),
                    ))
                }
            }
        }
    }
    let mut built = Vec::with_capacity(edges.len());
    for (path, number, f, tag) in edges {
        let (i, j) = (id(path, number, f[0], 1)?, id(path, number, f[1], 2)?);
        let information = edge_information(&f[5..])
            .ok_or_else(|| parse_error(path, number, "the covariance is not invertible"))?;
        built.push(Edge {
            factor: Box::new(BetweenSe2::new(i, j, Se2::new(f[2], f[3], f[4]))),
            information,
            label: format!("{tag} {i} {j} ({}:{number})", path.display()),
            path,
            line: number,
        });
    }
    order.extend(add_edges(
        &mut problem,
        built,
        Box::new(Se2::identity()),
        files[0].0,
    )?);
    if problem.values.is_empty() {
        return Err(IoError::Invalid {
            file: files[0].0.to_path_buf(),
            reason: "no vertices or edges".into(),
        });
    }
    Ok(PoseGraph {
        problem,
        dimension: Dimension::Two,
        vertex_order: order,
    })
}
