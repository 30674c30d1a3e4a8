//! TORO `.graph` files and the course's `.dat` pairs: `VERTEX2 id x y θ` and
//! `EDGE2 i j dx dy dθ I_xx I_xy I_yy I_tt I_xt I_yt` — information in TORO order
//! (xx xy yy tt xt yt), not g2o's. `EQUIV` (TORO's node merge directive) is ignored.

use std::path::Path;

use nalgebra::DMatrix;

use super::{id, lines, numbers, parse_error, problem_error, Dimension, IoError, PoseGraph};
use crate::factors::BetweenSe2;
use crate::geometry::Se2;
use crate::problem::Problem;

/// Ω from the six TORO fields `xx xy yy tt xt yt`.
pub fn information_from_toro(f: &[f64]) -> DMatrix<f64> {
    let (xx, xy, yy, tt, xt, yt) = (f[0], f[1], f[2], f[3], f[4], f[5]);
    DMatrix::from_row_slice(3, 3, &[xx, xy, xt, xy, yy, yt, xt, yt, tt])
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
    for (path, number, f, tag) in edges {
        let (i, j) = (id(path, number, f[0], 1)?, id(path, number, f[1], 2)?);
        let factor = BetweenSe2::new(i, j, Se2::new(f[2], f[3], f[4]));
        let label = format!("{tag} {i} {j} ({}:{number})", path.display());
        problem
            .add_factor(
                Box::new(factor),
                &information_from_toro(&f[5..]),
                None,
                label,
            )
            .map_err(|e| problem_error(path, number, e))?;
    }
    if problem.values.is_empty() {
        return Err(IoError::Invalid {
            file: files[0].0.to_path_buf(),
            reason: "no vertices".into(),
        });
    }
    Ok(PoseGraph {
        problem,
        dimension: Dimension::Two,
        vertex_order: order,
    })
}
