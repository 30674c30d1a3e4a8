//! Points lost behind their cameras, placed again.
//!
//! A bundle adjustment streamed camera by camera meets each point while few cameras see it, at
//! a small angle between their rays. Levenberg-Marquardt can then carry the point through
//! infinity: its rays are nearly parallel, and BAL's projection `p = −(P.x, P.y)/P.z` cannot
//! tell a point far ahead from one far behind. Past infinity the point sits behind every camera
//! that sees it, its gradient vanishes, and no later camera brings it back; the cameras it pulls
//! settle in a worse minimum. problem-49 streamed with calibration priors ended 7 % above the
//! batch optimum because two points sat 1.6 × 10⁶ behind the three and two cameras that see
//! them; with those two placed again, the same estimate solves to the optimum.
//!
//! COLMAP's incremental mapper re-triangulates points for the same reason. Here a point is
//! *lost* ([`lost_points`]) when it is behind every camera that sees it (built-in
//! `reprojection_snavely` factors; `P.z ≥ 0` in each camera frame), and it is placed again when
//! two or more cameras see it.
//! [`retriangulate`] triangulates points again from their observations with the cameras where
//! they are:
//!
//! ```text
//! ray of an observation z:  d = (x, y, −1),  x = z / (f (1 + k1 ‖x‖² + k2 ‖x‖⁴))  (undistorted)
//! linear triangulation:     min Σ ‖[d]× (R X + t)‖²  over X (the point on every ray)
//! then Gauss-Newton on X alone, on the factors' whitened residuals
//! ```
//!
//! The new place is kept only when it is in front of every camera that sees the point and
//! costs at most half of where the point is (and at least 1 less in chi2). BAL's files have
//! points that are behind their cameras at the optimum; those triangulate behind again and
//! keep their place.

use nalgebra::{Matrix3, Vector2, Vector3};

use crate::factors::ReprojectionSnavely;
use crate::geometry::{so3, Point3, SnavelyCamera};
use crate::problem::{FactorEntry, Problem};
use crate::variables::Variable;

/// Gauss-Newton iterations on a triangulated point (each one a 3×3 solve).
const REFINE_ITERATIONS: usize = 10;
/// A new place is kept when its cost is at most this fraction of the old place's…
const KEEP_BELOW: f64 = 0.5;
/// …and at least this much lower (chi2: whitened squared residuals): a point that fits within
/// the noise has nothing to gain.
const MIN_GAIN: f64 = 1.0;

/// The lost points of `problem` (see the module doc): behind every camera that sees them, and
/// free to move; [`retriangulate`] places those seen by two or more. Indices of variables, in
/// increasing order. One pass over the factors.
pub fn lost_points(problem: &Problem) -> Vec<usize> {
    let n = problem.values.len();
    let (mut seen, mut in_front) = (vec![false; n], vec![false; n]);
    for entry in problem.factors() {
        let Some(view) = View::of(problem, entry) else {
            continue;
        };
        let point = entry.variables()[1];
        seen[point] = true;
        in_front[point] |= view.camera.to_camera(&point_value(problem, point)).z < 0.0;
    }
    (0..n)
        .filter(|&v| seen[v] && !in_front[v] && !problem.values.is_fixed(v))
        .collect()
}

/// Triangulates each of `points` again from its cameras where they are, and keeps the new
/// place where it is in front of every camera that sees the point and costs at most half of
/// the old one and 1 less in chi2 (points seen by fewer than two cameras, or held fixed,
/// stay). Returns the indices of the variables moved, in increasing order.
pub fn retriangulate(problem: &mut Problem, points: &[usize]) -> Vec<usize> {
    let mut moved = Vec::new();
    for (point, entries) in observations_of(problem, points) {
        if problem.values.is_fixed(point) || distinct_cameras(problem, &entries) < 2 {
            continue;
        }
        let views: Vec<View> = entries
            .iter()
            .filter_map(|&e| View::of(problem, &problem.factors()[e]))
            .collect();
        let Some(start) = triangulate(&views) else {
            continue;
        };
        let refined = refine(problem, &entries, start);
        let in_front = views.iter().all(|v| v.camera.to_camera(&refined).z < 0.0);
        let old = cost_at(problem, &entries, point_value(problem, point));
        let new = cost_at(problem, &entries, refined);
        if in_front && new <= KEEP_BELOW * old && old - new >= MIN_GAIN {
            problem.values.set(point, &Point3(refined));
            moved.push(point);
        }
    }
    moved
}

/// The built-in reprojection factors of each of `points` that has any (in increasing order).
fn observations_of(problem: &Problem, points: &[usize]) -> Vec<(usize, Vec<usize>)> {
    if points.is_empty() {
        return Vec::new();
    }
    let mut wanted: Vec<Option<usize>> = vec![None; problem.values.len()];
    for (slot, &p) in points.iter().enumerate() {
        wanted[p] = Some(slot);
    }
    let mut seen_by: Vec<Vec<usize>> = vec![Vec::new(); points.len()];
    for (e, entry) in problem.factors().iter().enumerate() {
        if entry.factor.as_any().is::<ReprojectionSnavely>() {
            if let Some(slot) = wanted[entry.variables()[1]] {
                seen_by[slot].push(e);
            }
        }
    }
    let mut found: Vec<(usize, Vec<usize>)> = points
        .iter()
        .zip(seen_by)
        .filter(|(_, entries)| !entries.is_empty())
        .map(|(&p, entries)| (p, entries))
        .collect();
    found.sort_unstable_by_key(|(p, _)| *p);
    found.dedup_by_key(|(p, _)| *p);
    found
}

fn distinct_cameras(problem: &Problem, entries: &[usize]) -> usize {
    let mut cameras: Vec<usize> = entries
        .iter()
        .map(|&e| problem.factors()[e].variables()[0])
        .collect();
    cameras.sort_unstable();
    cameras.dedup();
    cameras.len()
}

/// One observation of a point: the camera that makes it and the pixel.
struct View {
    camera: SnavelyCamera,
    observed: Vector2<f64>,
}

impl View {
    /// The view a built-in reprojection factor makes, if `entry` is one.
    fn of(problem: &Problem, entry: &FactorEntry) -> Option<View> {
        let factor = entry
            .factor
            .as_any()
            .downcast_ref::<ReprojectionSnavely>()?;
        let camera = problem.values.variable(entry.variables()[0]);
        let camera = camera.as_any().downcast_ref::<SnavelyCamera>()?;
        Some(View {
            camera: *camera,
            observed: factor.observed,
        })
    }

    /// The ray's direction in the camera frame: the pixel undistorted (fixed-point iteration on
    /// `x = z / (f r(‖x‖²))`, which converges for BAL's small distortions) on the plane z = −1.
    fn ray(&self) -> Vector3<f64> {
        let c = &self.camera;
        let q = self.observed / c.focal;
        let mut x = q;
        for _ in 0..20 {
            let n = x.norm_squared();
            x = q / (1.0 + c.k1 * n + c.k2 * n * n);
        }
        Vector3::new(x.x, x.y, -1.0)
    }
}

/// The point nearest every view's ray (linear least squares), if the rays determine one.
fn triangulate(views: &[View]) -> Option<Vector3<f64>> {
    let mut normal = Matrix3::zeros();
    let mut rhs = Vector3::zeros();
    for view in views {
        // [d]× (R X + t) = 0: the point in the camera frame lies on the ray.
        let cross = so3::hat(&view.ray());
        let a = cross * view.camera.rotation.to_rotation_matrix().matrix();
        let b = -(cross * view.camera.translation);
        normal += a.transpose() * a;
        rhs += a.transpose() * b;
    }
    let eigen = normal.symmetric_eigen();
    let (low, high) = eigen
        .eigenvalues
        .iter()
        .fold((f64::INFINITY, 0.0_f64), |(l, h), &v| (l.min(v), h.max(v)));
    // Parallel rays leave the depth undetermined.
    if low.is_nan() || low <= 1e-12 * high {
        return None;
    }
    normal.cholesky().map(|c| c.solve(&rhs))
}

fn point_value(problem: &Problem, point: usize) -> Vector3<f64> {
    let variable: &dyn Variable = problem.values.variable(point);
    variable
        .as_any()
        .downcast_ref::<Point3>()
        .map_or_else(Vector3::zeros, |p| p.0)
}

/// The chi2 of `entries` with their point at `x` (the cameras where they are).
fn cost_at(problem: &Problem, entries: &[usize], x: Vector3<f64>) -> f64 {
    let point = Point3(x);
    let (mut error, mut whitened) = ([0.0; 2], [0.0; 2]);
    entries
        .iter()
        .map(|&e| {
            let entry = &problem.factors()[e];
            let camera = problem.values.variable(entry.variables()[0]);
            entry
                .chi2(&[camera, &point], &mut error, &mut whitened)
                .unwrap_or(f64::INFINITY)
        })
        .sum()
}

/// Gauss-Newton on the point alone from `start`, keeping only steps that lower the cost.
fn refine(problem: &Problem, entries: &[usize], start: Vector3<f64>) -> Vector3<f64> {
    let mut x = start;
    let mut cost = cost_at(problem, entries, x);
    for _ in 0..REFINE_ITERATIONS {
        let mut h = Matrix3::zeros();
        let mut g = Vector3::zeros();
        let point = Point3(x);
        for &e in entries {
            let entry = &problem.factors()[e];
            let camera = problem.values.variable(entry.variables()[0]);
            let (mut error, mut jacobian) = ([0.0; 2], [0.0; 24]);
            if entry
                .factor
                .evaluate(&[camera, &point], &mut error, Some(&mut jacobian))
                .is_err()
            {
                return x;
            }
            let mut j_point = [0.0; 6];
            for row in 0..2 {
                j_point[3 * row..3 * row + 3]
                    .copy_from_slice(&jacobian[12 * row + 9..12 * row + 12]);
            }
            let (mut we, mut wj) = ([0.0; 2], [0.0; 6]);
            entry.sqrt_information.whiten_vector(&error, &mut we);
            entry.sqrt_information.whiten_jacobian(&j_point, 3, &mut wj);
            for row in 0..2 {
                let jr = Vector3::new(wj[3 * row], wj[3 * row + 1], wj[3 * row + 2]);
                h += jr * jr.transpose();
                g += jr * we[row];
            }
        }
        let Some(step) = h.cholesky().map(|c| c.solve(&-g)) else {
            return x;
        };
        let next = x + step;
        let next_cost = cost_at(problem, entries, next);
        if next_cost.is_nan() || next_cost >= cost {
            return x;
        }
        (x, cost) = (next, next_cost);
    }
    x
}

#[cfg(test)]
mod tests {
    use nalgebra::{UnitQuaternion, Vector2, Vector3};

    use super::*;
    use crate::factors::SqrtInformation;
    use crate::geometry::{Point3, SnavelyCamera};

    /// Camera `camera` sees point `point` at `pixel` (σ 1 pixel).
    fn observe(problem: &mut Problem, camera: u64, point: u64, pixel: Vector2<f64>) {
        let factor = ReprojectionSnavely::new(camera, point, pixel);
        let unit = SqrtInformation::identity(2);
        problem
            .add_factor_sqrt(Box::new(factor), unit, None, String::new())
            .unwrap();
    }

    /// Three cameras on a line looking down −z at points 5 m ahead; point 0 sits 10⁶ behind
    /// them on its rays (lost), point 1 where it belongs.
    fn scene() -> (Problem, Vec<Vector3<f64>>) {
        let mut problem = Problem::new().eliminating(&["point3"]);
        let truth = vec![Vector3::new(0.3, -0.2, -5.0), Vector3::new(-0.4, 0.1, -6.0)];
        let cameras: Vec<SnavelyCamera> = (0..3)
            .map(|i| SnavelyCamera {
                rotation: UnitQuaternion::from_euler_angles(0.0, 0.02 * i as f64, 0.0),
                translation: Vector3::new(-0.5 * i as f64, 0.0, 0.0),
                focal: 500.0,
                k1: 0.01,
                k2: 0.0,
            })
            .collect();
        for (i, camera) in cameras.iter().enumerate() {
            problem.add_variable(i as u64, Box::new(*camera)).unwrap();
        }
        for (j, x) in truth.iter().enumerate() {
            let at = if j == 0 {
                // Through infinity: far behind, near where the rays from the first camera point.
                cameras[0].centre() - (x - cameras[0].centre()) * 2e5
            } else {
                *x
            };
            problem
                .add_variable(10 + j as u64, Box::new(Point3(at)))
                .unwrap();
            for (i, camera) in cameras.iter().enumerate() {
                observe(&mut problem, i as u64, 10 + j as u64, camera.project(x));
            }
        }
        (problem, truth)
    }

    #[test]
    fn a_point_lost_behind_its_cameras_is_placed_on_its_rays_and_others_stay() {
        let (mut problem, truth) = scene();
        let before = point_value(&problem, 4);
        let lost = lost_points(&problem);
        assert_eq!(lost, vec![3], "only point 0 is behind its cameras");
        let moved = retriangulate(&mut problem, &lost);
        assert_eq!(moved, vec![3], "only the lost point moves");
        assert!((point_value(&problem, 3) - truth[0]).norm() < 1e-6);
        assert_eq!(point_value(&problem, 4), before);
        assert!(problem.chi2() < 1e-12, "chi2 {}", problem.chi2());
    }

    #[test]
    fn a_point_behind_at_its_best_place_keeps_it() {
        let (mut problem, _) = scene();
        let lost = lost_points(&problem);
        retriangulate(&mut problem, &lost);
        // A point whose observations put it behind the cameras (a BAL file has some at the
        // optimum) triangulates behind again: it is not moved.
        let behind = Vector3::new(0.2, 0.1, 4.0);
        problem.add_variable(20, Box::new(Point3(behind))).unwrap();
        for i in 0..3u64 {
            let camera = *problem.values.get_as::<SnavelyCamera>(i).unwrap();
            observe(&mut problem, i, 20, camera.project(&behind));
        }
        assert_eq!(lost_points(&problem), vec![5]);
        assert!(retriangulate(&mut problem, &[5]).is_empty());
        // Nor is a point where it belongs, which no triangulation fits twice better.
        assert!(retriangulate(&mut problem, &[3, 4]).is_empty());
    }

    #[test]
    fn a_point_in_front_but_off_its_rays_is_placed_on_them_when_asked() {
        let (mut problem, truth) = scene();
        problem
            .values
            .set(4, &Point3(Vector3::new(-1.0, 0.5, -2.0)));
        assert!(
            !lost_points(&problem).contains(&4),
            "in front of its cameras: not lost"
        );
        assert_eq!(retriangulate(&mut problem, &[4]), vec![4]);
        assert!((point_value(&problem, 4) - truth[1]).norm() < 1e-6);
    }
}
