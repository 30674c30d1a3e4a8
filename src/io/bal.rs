//! Bundle Adjustment in the Large (BAL) files: `<cameras> <points> <observations>`, then one
//! `<camera> <point> <x> <y>` per observation, then 9 parameters per camera (angle-axis, t, f,
//! k1, k2) and 3 coordinates per point, whitespace separated (see `geometry::camera` for the
//! model). Every number is checked: a truncated file, wrong counts, an index out of range or a
//! non-finite value is an error naming the line and what was expected there.

use std::path::{Path, PathBuf};

use nalgebra::{DMatrix, Vector2, Vector3};

use super::{parse_error, problem_error, read_text, IoError};
use crate::factors::ReprojectionSnavely;
use crate::geometry::{so3, Point3, SnavelyCamera};
use crate::problem::{Gauge, Key, Problem};

/// A BAL problem: camera `i` has key `i`, point `j` has key `num_cameras + j`.
#[derive(Debug)]
pub struct BalProblem {
    pub problem: Problem,
    pub num_cameras: usize,
    pub num_points: usize,
}

impl BalProblem {
    pub fn camera_key(&self, i: usize) -> Key {
        i as Key
    }
    pub fn point_key(&self, j: usize) -> Key {
        (self.num_cameras + j) as Key
    }

    /// BAL's cost convention, ½Σ‖e‖² (Ceres prints this), at the current values.
    pub fn cost(&self) -> f64 {
        0.5 * self.problem.chi2()
    }

    fn update<T: crate::problem::Variable + Copy>(
        &mut self,
        key: Key,
        change: impl FnOnce(&mut T),
    ) {
        let idx = self.problem.values.index_of(key).expect("BAL keys exist");
        let mut value = *self
            .problem
            .values
            .get_as::<T>(key)
            .expect("BAL keys hold their kind");
        change(&mut value);
        self.problem.values.set(idx, &value);
    }

    pub fn points(&self) -> Vec<Vector3<f64>> {
        (0..self.num_points)
            .map(|j| {
                self.problem
                    .values
                    .get_as::<Point3>(self.point_key(j))
                    .expect("point keys hold points")
                    .0
            })
            .collect()
    }

    pub fn camera_centres(&self) -> Vec<Vector3<f64>> {
        (0..self.num_cameras)
            .map(|i| {
                self.problem
                    .values
                    .get_as::<SnavelyCamera>(self.camera_key(i))
                    .expect("camera keys hold cameras")
                    .centre()
            })
            .collect()
    }

    /// Ceres' `BALProblem::Normalize`: centre the points on their per-coordinate median and scale
    /// the scene so that the median L1 distance of the points to it is 100; cameras keep their
    /// orientation, their centres move with the points.
    pub fn normalize(&mut self) {
        let points = self.points();
        if points.is_empty() {
            return;
        }
        let centre = Vector3::from_fn(|c, _| median(points.iter().map(|p| p[c]).collect()));
        let deviation = median(points.iter().map(|p| (p - centre).lp_norm(1)).collect());
        let scale = if deviation > 0.0 {
            100.0 / deviation
        } else {
            1.0
        };
        for j in 0..self.num_points {
            self.update(self.point_key(j), |p: &mut Point3| {
                p.0 = (p.0 - centre) * scale
            });
        }
        for i in 0..self.num_cameras {
            self.update(self.camera_key(i), |camera: &mut SnavelyCamera| {
                camera.translation = -(camera.rotation * ((camera.centre() - centre) * scale));
            });
        }
    }

    /// Ceres' `BALProblem::Perturb`: Gaussian noise of the given standard deviations on each
    /// camera's angle-axis rotation and centre, and on each point (zero skips that part).
    pub fn perturb(
        &mut self,
        rotation_sigma: f64,
        translation_sigma: f64,
        point_sigma: f64,
        seed: u64,
    ) {
        let mut rng = crate::factors::testing::Rng::new(seed);
        let mut noise = |sigma: f64| Vector3::new(rng.normal(), rng.normal(), rng.normal()) * sigma;
        for j in 0..self.num_points {
            if point_sigma > 0.0 {
                let n = noise(point_sigma);
                self.update(self.point_key(j), |p: &mut Point3| p.0 += n);
            }
        }
        for i in 0..self.num_cameras {
            let (dr, dc) = (noise(rotation_sigma), noise(translation_sigma));
            self.update(self.camera_key(i), |camera: &mut SnavelyCamera| {
                let mut centre = camera.centre();
                if rotation_sigma > 0.0 {
                    camera.rotation = so3::exp(&(so3::log(&camera.rotation) + dr));
                }
                if translation_sigma > 0.0 {
                    centre += dc;
                }
                camera.translation = -(camera.rotation * centre);
            });
        }
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Whitespace-separated numbers with the line each came from.
struct Tokens<'a> {
    path: &'a Path,
    items: Vec<(usize, &'a str)>,
    next: usize,
}

impl<'a> Tokens<'a> {
    fn new(path: &'a Path, text: &'a str) -> Self {
        let items = super::without_bom(text)
            .lines()
            .enumerate()
            .flat_map(|(i, l)| l.split_whitespace().map(move |t| (i + 1, t)))
            .collect();
        Self {
            path,
            items,
            next: 0,
        }
    }

    fn number(&mut self, what: &str) -> Result<f64, IoError> {
        let Some(&(line, token)) = self.items.get(self.next) else {
            let line = self.items.last().map_or(1, |&(l, _)| l);
            return Err(parse_error(
                self.path,
                line,
                format!("file ends where {what} was expected"),
            ));
        };
        self.next += 1;
        match token.parse::<f64>() {
            Ok(v) if v.is_finite() => Ok(v),
            Ok(_) => Err(parse_error(
                self.path,
                line,
                format!("{what} (`{token}`) is not finite"),
            )),
            Err(_) => Err(parse_error(
                self.path,
                line,
                format!("{what} (`{token}`) is not a number"),
            )),
        }
    }

    fn index(&mut self, what: &str, bound: usize) -> Result<usize, IoError> {
        let line = self.items.get(self.next).map_or(0, |&(l, _)| l);
        let v = self.number(what)?;
        if v < 0.0 || v.fract() != 0.0 || v >= bound as f64 {
            return Err(parse_error(
                self.path,
                line,
                format!("{what} `{v}` is not an index below {bound}"),
            ));
        }
        Ok(v as usize)
    }

    fn count(&mut self, what: &str) -> Result<usize, IoError> {
        self.index(what, 1 << 40)
    }

    fn finish(&self) -> Result<(), IoError> {
        match self.items.get(self.next) {
            Some(&(line, token)) => Err(parse_error(
                self.path,
                line,
                format!("unexpected `{token}` after the last point: the counts in the header do not match the data"),
            )),
            None => Ok(()),
        }
    }
}

/// Parses a BAL problem held in memory (`path` labels errors).
pub fn parse(path: &Path, text: &str) -> Result<BalProblem, IoError> {
    let mut tokens = Tokens::new(path, text);
    let num_cameras = tokens.count("the number of cameras")?;
    let num_points = tokens.count("the number of points")?;
    let num_observations = tokens.count("the number of observations")?;
    let expected = 3 + 4 * num_observations + 9 * num_cameras + 3 * num_points;
    if tokens.items.len() < expected {
        let line = tokens.items.last().map_or(1, |&(l, _)| l);
        return Err(parse_error(
            path,
            line,
            format!(
                "the header announces {num_cameras} cameras, {num_points} points and {num_observations} observations ({expected} numbers), the file has {}",
                tokens.items.len()
            ),
        ));
    }
    let mut observations = Vec::with_capacity(num_observations);
    for k in 0..num_observations {
        let camera = tokens.index(&format!("observation {k}'s camera"), num_cameras)?;
        let point = tokens.index(&format!("observation {k}'s point"), num_points)?;
        let x = tokens.number(&format!("observation {k}'s x"))?;
        let y = tokens.number(&format!("observation {k}'s y"))?;
        observations.push((camera, point, Vector2::new(x, y)));
    }
    let mut problem = Problem::new();
    problem.gauge = Gauge::Free;
    problem.eliminate = vec!["point3"];
    for i in 0..num_cameras {
        let mut p = [0.0; 9];
        for (c, v) in p.iter_mut().enumerate() {
            *v = tokens.number(&format!("camera {i}'s parameter {c}"))?;
        }
        problem
            .add_variable(i as Key, Box::new(SnavelyCamera::from_bal(&p)))
            .map_err(|e| problem_error(path, 1, e))?;
    }
    for j in 0..num_points {
        let mut x = [0.0; 3];
        for (c, v) in x.iter_mut().enumerate() {
            *v = tokens.number(&format!("point {j}'s coordinate {c}"))?;
        }
        let key = (num_cameras + j) as Key;
        problem
            .add_variable(key, Box::new(Point3(Vector3::from(x))))
            .map_err(|e| problem_error(path, 1, e))?;
    }
    tokens.finish()?;
    let unit = DMatrix::identity(2, 2);
    for (k, (camera, point, z)) in observations.into_iter().enumerate() {
        let factor = ReprojectionSnavely::new(camera as Key, (num_cameras + point) as Key, z);
        problem
            .add_factor(Box::new(factor), &unit, None, format!("observation {k}"))
            .map_err(|e| problem_error(path, 1, e))?;
    }
    Ok(BalProblem {
        problem,
        num_cameras,
        num_points,
    })
}

pub fn load(path: &Path) -> Result<BalProblem, IoError> {
    parse(path, &read_text(path)?)
}

/// The problem in BAL form (observations, then cameras and points at their current values).
pub fn to_string(bal: &BalProblem) -> String {
    use std::fmt::Write as _;
    let problem = &bal.problem;
    let mut out = format!(
        "{} {} {}\n",
        bal.num_cameras,
        bal.num_points,
        problem.factors().len()
    );
    for f in problem.factors() {
        let z = f
            .factor
            .as_any()
            .downcast_ref::<ReprojectionSnavely>()
            .expect("BAL problems hold reprojection factors")
            .observed;
        let keys = f.factor.keys();
        let _ = writeln!(
            out,
            "{} {} {:e} {:e}",
            keys[0],
            keys[1] as usize - bal.num_cameras,
            z.x,
            z.y
        );
    }
    for i in 0..bal.num_cameras {
        let camera = problem
            .values
            .get_as::<SnavelyCamera>(bal.camera_key(i))
            .expect("camera keys hold cameras");
        for v in camera.to_bal() {
            let _ = writeln!(out, "{v:e}");
        }
    }
    for j in 0..bal.num_points {
        let point = problem
            .values
            .get_as::<Point3>(bal.point_key(j))
            .expect("point keys hold points");
        for v in point.0.iter() {
            let _ = writeln!(out, "{v:e}");
        }
    }
    out
}

pub fn write(bal: &BalProblem, path: &Path) -> Result<(), IoError> {
    std::fs::write(path, to_string(bal)).map_err(|source| IoError::Write {
        file: PathBuf::from(path),
        source,
    })
}
