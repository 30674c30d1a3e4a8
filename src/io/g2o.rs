//! g2o files: `VERTEX_SE2`, `EDGE_SE2`, `VERTEX_SE3:QUAT`, `EDGE_SE3:QUAT`, `FIX`, and planar
//! landmarks: `VERTEX_XY key x y` (g2o's tag) with
//! `EDGE_BEARING_RANGE_SE2_XY pose landmark bearing range Ω_bb Ω_br Ω_rr` (bearing in radians, range
//! in metres, information upper triangle as every edge), our own record for the bearing-range
//! sightings of GTSAM's landmark text (g2o has a bearing-only `EDGE_BEARING_SE2_XY`, no
//! bearing-range edge), so a solved `victoria_park.txt` written with `--out` reads back as the
//! same problem. Every id is read as an exact 64-bit integer: GTSAM's symbol keys (a landmark's
//! `('l' << 56) | l`, a robot's pose `('a' << 56) | i`) are beyond f64's integers, so a file of
//! several robots (docs/guide/many-robots.md, "Files of several robots") reads as it was written.
//!
//! Information matrices are the upper triangle, row-major. For 3D the file's Ω (order t, R) is
//! defined on g2o's error `[t; vec(q)]`, where `vec(q) ≈ Log(R)/2`; our SE(3) factor's rotation
//! error is `Log(R)` (the angle), so Ω is mapped to `D Ω D`, `D = diag(1, 1, 1, ½, ½, ½)`, and back
//! on writing. [`chi2_g2o_convention`] scores a 3D graph exactly as g2o does, for comparisons.
//! A file of edges only gets its vertices from a spanning tree (`edges.rs`).

use std::fmt::Write as _;
use std::path::Path;

use nalgebra::{DMatrix, Quaternion, UnitQuaternion, Vector3};

use super::edges::{add_edges, Edge};
use super::{key_field, lines, numbers, parse_error, problem_error, Dimension, IoError, PoseGraph};
use crate::factors::{BearingRangeSe2, BetweenSe2, BetweenSe3};
use crate::geometry::{Point2, Se2, Se3};
use crate::problem::FactorEntry;
use crate::problem::{Key, Problem, Values, Variable};
use nalgebra::Vector2;

/// Symmetric n×n from its upper triangle, row-major.
fn upper_triangle(n: usize, f: &[f64]) -> DMatrix<f64> {
    let mut m = DMatrix::zeros(n, n);
    let mut k = 0;
    for i in 0..n {
        for j in i..n {
            m[(i, j)] = f[k];
            m[(j, i)] = f[k];
            k += 1;
        }
    }
    m
}

/// `D = diag(1, 1, 1, ½, ½, ½)` maps g2o's 3D information onto our error.
fn rotation_scaling(half: bool) -> DMatrix<f64> {
    let s = if half { 0.5 } else { 2.0 };
    DMatrix::from_diagonal(&nalgebra::DVector::from_row_slice(&[
        1.0, 1.0, 1.0, s, s, s,
    ]))
}

fn quaternion(path: &Path, number: usize, f: &[f64]) -> Result<UnitQuaternion<f64>, IoError> {
    let q = Quaternion::new(f[3], f[0], f[1], f[2]);
    let norm = q.norm();
    if !(0.5..=2.0).contains(&norm) {
        return Err(parse_error(
            path,
            number,
            format!("quaternion norm {norm} is far from 1"),
        ));
    }
    Ok(UnitQuaternion::from_quaternion(q))
}

/// An EDGE_SE2 / EDGE_SE3:QUAT record: file, line, (i, j), its numbers, its dimension.
type EdgeRecord<'a> = (&'a Path, usize, (Key, Key), Vec<f64>, Dimension);

/// What the records of a g2o text add up to before the edges are built.
#[derive(Default)]
struct Records<'a> {
    problem: Problem,
    order: Vec<Key>,
    /// Each EDGE_SE2 / EDGE_SE3:QUAT.
    edges: Vec<EdgeRecord<'a>>,
    /// (file, line, pose, landmark, numbers) of each EDGE_BEARING_RANGE_SE2_XY.
    sightings: Vec<(&'a Path, usize, Key, Key, Vec<f64>)>,
    fixes: Vec<(&'a Path, usize, Key)>,
}

pub fn parse(files: &[(&Path, &str)]) -> Result<PoseGraph, IoError> {
    let mut records = Records::default();
    let mut dimension = None;
    for &(path, text) in files {
        for line in lines(text) {
            if let Some(d) = records.read(path, &line)? {
                if dimension.is_some_and(|seen| seen != d) {
                    return Err(parse_error(path, line.number, "mixes 2D and 3D records"));
                }
                dimension = Some(d);
            }
        }
    }
    let Some(dimension) = dimension else {
        return Err(super::IoError::Invalid {
            file: files[0].0.to_path_buf(),
            reason: "no vertices or edges".into(),
        });
    };
    let Records {
        mut problem,
        mut order,
        edges,
        sightings,
        fixes,
    } = records;
    let mut built = between_edges(edges)?;
    built.extend(sighting_edges(sightings)?);
    let origin: Box<dyn Variable> = match dimension {
        Dimension::Two => Box::new(Se2::identity()),
        Dimension::Three => Box::new(Se3::identity()),
    };
    order.extend(add_edges(&mut problem, built, origin, files[0].0)?);
    for (path, number, key) in fixes {
        problem
            .set_fixed(key, true)
            .map_err(|e| problem_error(path, number, e))?;
    }
    Ok(PoseGraph {
        problem,
        dimension,
        vertex_order: order,
    })
}

impl<'a> Records<'a> {
    /// Reads one record: vertices go into the problem, edges and fixes are kept for later.
    /// Returns the dimension the record belongs to (none for FIX).
    fn read(&mut self, path: &'a Path, line: &super::Line) -> Result<Option<Dimension>, IoError> {
        let number = line.number;
        Ok(match line.tokens[0] {
            "VERTEX_SE2" => {
                let f = numbers(path, line, 4)?;
                let key = key_field(path, line, 1)?;
                self.vertex(path, number, key, Box::new(Se2::new(f[1], f[2], f[3])))?;
                Some(Dimension::Two)
            }
            "VERTEX_XY" => {
                let f = numbers(path, line, 3)?;
                let key = key_field(path, line, 1)?;
                self.vertex(
                    path,
                    number,
                    key,
                    Box::new(Point2(Vector2::new(f[1], f[2]))),
                )?;
                Some(Dimension::Two)
            }
            "EDGE_BEARING_RANGE_SE2_XY" => {
                let f = numbers(path, line, 7)?;
                let (pose, landmark) = (key_field(path, line, 1)?, key_field(path, line, 2)?);
                self.sightings.push((path, number, pose, landmark, f));
                Some(Dimension::Two)
            }
            "VERTEX_SE3:QUAT" => {
                let f = numbers(path, line, 8)?;
                let key = key_field(path, line, 1)?;
                let q = quaternion(path, number, &f[4..8])?;
                let pose = Se3::new(q, Vector3::new(f[1], f[2], f[3]));
                self.vertex(path, number, key, Box::new(pose))?;
                Some(Dimension::Three)
            }
            "EDGE_SE2" => {
                let f = numbers(path, line, 11)?;
                let ends = (key_field(path, line, 1)?, key_field(path, line, 2)?);
                self.edges.push((path, number, ends, f, Dimension::Two));
                Some(Dimension::Two)
            }
            "EDGE_SE3:QUAT" => {
                let f = numbers(path, line, 30)?;
                let ends = (key_field(path, line, 1)?, key_field(path, line, 2)?);
                self.edges.push((path, number, ends, f, Dimension::Three));
                Some(Dimension::Three)
            }
            "FIX" => {
                for (field, t) in line.tokens.iter().enumerate().skip(1) {
                    if t.parse::<f64>().is_err() {
                        let message = format!("FIX field {field} (`{t}`) is not an id");
                        return Err(parse_error(path, number, message));
                    }
                    self.fixes
                        .push((path, number, key_field(path, line, field)?));
                }
                None
            }
            other => {
                return Err(parse_error(
                    path,
                    number,
                    format!("unsupported record `{other}`"),
                ));
            }
        })
    }

    fn vertex(
        &mut self,
        path: &Path,
        number: usize,
        key: Key,
        value: Box<dyn Variable>,
    ) -> Result<(), IoError> {
        self.problem
            .add_variable(key, value)
            .map_err(|e| problem_error(path, number, e))?;
        self.order.push(key);
        Ok(())
    }
}

/// The EDGE_SE2 / EDGE_SE3:QUAT records as between factors.
fn between_edges(edges: Vec<EdgeRecord<'_>>) -> Result<Vec<Edge<'_>>, IoError> {
    let mut built = Vec::with_capacity(edges.len());
    for (path, number, (i, j), f, dim) in edges {
        built.push(match dim {
            Dimension::Two => Edge {
                factor: Box::new(BetweenSe2::new(i, j, Se2::new(f[2], f[3], f[4]))),
                information: upper_triangle(3, &f[5..11]),
                label: format!("EDGE_SE2 {i} {j} ({}:{number})", path.display()),
                path,
                line: number,
            },
            Dimension::Three => {
                let z = Se3::new(
                    quaternion(path, number, &f[5..9])?,
                    Vector3::new(f[2], f[3], f[4]),
                );
                let d = rotation_scaling(true);
                Edge {
                    factor: Box::new(BetweenSe3::new(i, j, z)),
                    information: &d * upper_triangle(6, &f[9..30]) * &d,
                    label: format!("EDGE_SE3:QUAT {i} {j} ({}:{number})", path.display()),
                    path,
                    line: number,
                }
            }
        });
    }
    Ok(built)
}

/// The EDGE_BEARING_RANGE_SE2_XY records as bearing-range factors.
fn sighting_edges(
    sightings: Vec<(&Path, usize, Key, Key, Vec<f64>)>,
) -> Result<Vec<Edge<'_>>, IoError> {
    let mut built = Vec::with_capacity(sightings.len());
    for (path, number, pose, landmark, f) in sightings {
        if f[3] < 0.0 {
            return Err(parse_error(path, number, "a range cannot be negative"));
        }
        built.push(Edge {
            factor: Box::new(BearingRangeSe2::new(pose, landmark, f[2], f[3])),
            information: upper_triangle(2, &f[4..7]),
            label: format!(
                "EDGE_BEARING_RANGE_SE2_XY {pose} {landmark} ({}:{number})",
                path.display()
            ),
            path,
            line: number,
        });
    }
    Ok(built)
}

fn information_upper(m: &DMatrix<f64>) -> String {
    let mut s = String::new();
    for i in 0..m.nrows() {
        for j in i..m.ncols() {
            let _ = write!(s, " {}", m[(i, j)]);
        }
    }
    s
}

/// The graph as g2o text, vertices with their current values.
pub fn to_string(graph: &PoseGraph) -> String {
    to_string_marking(graph, &[])
}

/// [`to_string`] with the factors at the (ascending) indices `rejected` written as comments,
/// `# rejected: EDGE_…`: they stay visible, and reading the file back gives the graph that was
/// solved once they were rejected.
pub fn to_string_marking(graph: &PoseGraph, rejected: &[usize]) -> String {
    let values = &graph.problem.values;
    let mut out = String::new();
    for &key in &graph.vertex_order {
        if let Some(p) = values.get_as::<Se2>(key) {
            let _ = writeln!(out, "VERTEX_SE2 {key} {} {} {}", p.x, p.y, p.theta);
        } else if let Some(p) = values.get_as::<Point2>(key) {
            let _ = writeln!(out, "VERTEX_XY {key} {} {}", p.0.x, p.0.y);
        } else if let Some(p) = values.get_as::<Se3>(key) {
            let (t, q) = (p.translation, p.rotation);
            let _ = writeln!(
                out,
                "VERTEX_SE3:QUAT {key} {} {} {} {} {} {} {}",
                t.x, t.y, t.z, q.i, q.j, q.k, q.w
            );
        }
    }
    for (index, f) in graph.problem.factors().iter().enumerate() {
        let mark = if rejected.binary_search(&index).is_ok() {
            "# rejected: "
        } else {
            ""
        };
        let keys = f.factor.keys();
        let info = f.sqrt_information.information();
        if let Some(b) = f.factor.as_any().downcast_ref::<BetweenSe2>() {
            let z = b.measurement;
            let _ = writeln!(
                out,
                "{mark}EDGE_SE2 {} {} {} {} {}{}",
                keys[0],
                keys[1],
                z.x,
                z.y,
                z.theta,
                information_upper(&info)
            );
        } else if let Some(b) = f.factor.as_any().downcast_ref::<BearingRangeSe2>() {
            let _ = writeln!(
                out,
                "{mark}EDGE_BEARING_RANGE_SE2_XY {} {} {} {}{}",
                keys[0],
                keys[1],
                b.bearing,
                b.range,
                information_upper(&info)
            );
        } else if let Some(b) = f.factor.as_any().downcast_ref::<BetweenSe3>() {
            let (t, q) = (b.measurement.translation, b.measurement.rotation);
            let d = rotation_scaling(false);
            let _ = writeln!(
                out,
                "{mark}EDGE_SE3:QUAT {} {} {} {} {} {} {} {} {}{}",
                keys[0],
                keys[1],
                t.x,
                t.y,
                t.z,
                q.i,
                q.j,
                q.k,
                q.w,
                information_upper(&(&d * info * &d))
            );
        } else {
            // Visible rather than silently missing: the file then reads back without it.
            let _ = writeln!(out, "# not written (no g2o record for it): {}", f.label);
        }
    }
    let fixed: Vec<Key> = (0..values.len())
        .filter(|&v| values.is_fixed(v))
        .map(|v| values.key(v))
        .collect();
    if !fixed.is_empty() {
        let ids: Vec<String> = fixed.iter().map(|k| k.to_string()).collect();
        let _ = writeln!(out, "FIX {}", ids.join(" "));
    }
    out
}

pub fn write(graph: &PoseGraph, path: &Path) -> Result<(), IoError> {
    std::fs::write(path, to_string(graph)).map_err(|source| IoError::Write {
        file: path.to_path_buf(),
        source,
    })
}

/// chi2 as g2o computes it: 2D is identical to ours; for 3D the error is `[t_E; vec(q_E)]` with
/// `q_E` taken with w ≥ 0 and the file's (unmapped) information.
pub fn chi2_g2o_convention(factors: &[FactorEntry], values: &Values) -> f64 {
    let d = rotation_scaling(false);
    let mut total = 0.0;
    for f in factors {
        let keys = f.factor.keys();
        if let Some(b) = f.factor.as_any().downcast_ref::<BetweenSe3>() {
            let (Some(xi), Some(xj)) =
                (values.get_as::<Se3>(keys[0]), values.get_as::<Se3>(keys[1]))
            else {
                continue;
            };
            let e = b.measurement.inverse().compose(&xi.between(xj));
            let q = e.rotation.quaternion();
            let s = if q.w < 0.0 { -1.0 } else { 1.0 };
            let err = nalgebra::DVector::from_row_slice(&[
                e.translation.x,
                e.translation.y,
                e.translation.z,
                s * q.i,
                s * q.j,
                s * q.k,
            ]);
            let info = &d * f.sqrt_information.information() * &d;
            total += (err.transpose() * info * &err)[(0, 0)];
        } else {
            let refs: Vec<&dyn crate::problem::Variable> =
                keys.iter().filter_map(|&k| values.get(k)).collect();
            let dim = f.factor.residual_dim();
            let (mut e, mut w) = (vec![0.0; dim], vec![0.0; dim]);
            total += f.chi2(&refs, &mut e, &mut w).unwrap_or(f64::NAN);
        }
    }
    total
}
