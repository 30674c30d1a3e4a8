//! The before/after picture of a batch solve as one SVG, the static twin of the web view: the
//! trajectory (initial guess and optimum, loop closures of the optimum) next to the convergence
//! plot (χ² per iteration on a log scale).
//!
//! Positions come from [`Variable::position`](crate::variables::Variable::position); 3D graphs (any z ≠ 0) are drawn from above (x-y)
//! and from the side (x-z), each panel with its axes' tick labels in metres. Poses are the
//! trajectory line; landmarks (kinds drawn as [`Shape::Landmark`], Victoria Park's trees) are dots
//! of their own, never part of the line. Loop closures are factors between two poses that are
//! not neighbours in key order (ids may skip: Victoria Park's poses skip the ids its landmarks
//! had; a landmark sighting is none), as the web view counts them.

use std::fmt::Write as _;
use std::path::Path;

use super::IoError;
use crate::problem::FactorEntry;
use crate::problem::Values;
use crate::solver::Summary;
use crate::variables::{point2, point3, Shape, Variable};

const PANEL: f64 = 560.0;
const MARGIN: f64 = 64.0;
/// Below the panels: tick labels, axis name, legend.
const AXIS_ROOM: f64 = 40.0;
const INITIAL: &str = "#e8a33d";
const OPTIMUM: &str = "#1f4e9c";
const LOOP: &str = "#c0392b";
const LANDMARK: &str = "#2e8b57";

/// The picture of `initial` → `optimum` with `summary`'s iterations.
pub fn before_after(
    initial: &Values,
    optimum: &Values,
    factors: &[FactorEntry],
    summary: &Summary,
    title: &str,
) -> String {
    let (before, after) = (positions(initial), positions(optimum));
    let landmark: Vec<bool> = (0..optimum.len())
        .map(|v| is_landmark(optimum.variable(v)))
        .collect();
    let rank = pose_ranks(optimum, &landmark);
    let has_height = before.iter().chain(&after).flatten().any(|p| p[2] != 0.0);
    let views: &[View] = if has_height {
        &[View::TOP, View::SIDE]
    } else {
        &[View::TOP]
    };
    let panels = views.len() as f64 + 1.0;
    let width = panels * PANEL + (panels + 1.0) * MARGIN;
    let height = PANEL + 2.0 * MARGIN + AXIS_ROOM;
    let mut svg = String::new();
    let _ = writeln!(
        svg,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" viewBox="0 0 {width} {height}" font-family="sans-serif" font-size="13">"#
    );
    let _ = writeln!(svg, r#"<rect width="100%" height="100%" fill="white"/>"#);
    let _ = writeln!(
        svg,
        r#"<text x="{MARGIN}" y="24" font-size="15">{}</text>"#,
        escape(title)
    );
    let mut left = MARGIN;
    for view in views {
        let drawn = Drawn {
            before: &before,
            after: &after,
            factors,
            landmark: &landmark,
            rank: &rank,
        };
        trajectory(&mut svg, &drawn, *view, left, MARGIN);
        left += PANEL + MARGIN;
    }
    convergence(&mut svg, summary, left, MARGIN);
    svg.push_str("</svg>\n");
    svg
}

pub fn write(path: &Path, svg: &str) -> Result<(), IoError> {
    std::fs::write(path, svg).map_err(|source| IoError::Write {
        file: path.into(),
        source,
    })
}

fn escape(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

fn positions(values: &Values) -> Vec<Option<[f64; 3]>> {
    (0..values.len())
        .map(|v| values.variable(v).position())
        .collect()
}

/// Whether `variable` is drawn as a landmark dot rather than a point of the trajectory.
fn is_landmark(variable: &dyn Variable) -> bool {
    [point2::WIRE, point3::WIRE]
        .iter()
        .any(|wire| wire.kind == variable.kind() && wire.shape == Shape::Landmark)
}

/// Each variable's place among the poses sorted by key (landmarks get `usize::MAX`): two poses
/// one place apart are odometry neighbours, whatever ids lie between them.
fn pose_ranks(values: &Values, landmark: &[bool]) -> Vec<usize> {
    let mut poses: Vec<usize> = (0..values.len()).filter(|&v| !landmark[v]).collect();
    poses.sort_by_key(|&v| values.key(v));
    let mut rank = vec![usize::MAX; values.len()];
    for (place, v) in poses.into_iter().enumerate() {
        rank[v] = place;
    }
    rank
}

/// `positions` split by `landmark` (one flag per variable): the trajectory's points in variable
/// order, and the landmarks' points.
fn split(positions: &[Option<[f64; 3]>], landmark: &[bool]) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let (mut path, mut dots) = (Vec::new(), Vec::new());
    for (p, &is_landmark) in positions.iter().zip(landmark) {
        if let Some(p) = p {
            if is_landmark {
                dots.push(*p);
            } else {
                path.push(*p);
            }
        }
    }
    (path, dots)
}

/// A projection of the world: which two axes the panel shows, and their names.
#[derive(Clone, Copy)]
struct View {
    axes: [usize; 2],
    names: [&'static str; 2],
    label: &'static str,
}

impl View {
    const TOP: Self = Self {
        axes: [0, 1],
        names: ["x (m)", "y (m)"],
        label: "from above",
    };
    const SIDE: Self = Self {
        axes: [0, 2],
        names: ["x (m)", "z (m)"],
        label: "from the side",
    };

    fn project(&self, p: &[f64; 3]) -> [f64; 2] {
        [p[self.axes[0]], p[self.axes[1]]]
    }
}

/// What a trajectory panel draws.
struct Drawn<'a> {
    before: &'a [Option<[f64; 3]>],
    after: &'a [Option<[f64; 3]>],
    factors: &'a [FactorEntry],
    /// Per variable: drawn as a landmark dot.
    landmark: &'a [bool],
    /// Per variable: its place among the poses in key order (see [`pose_ranks`]).
    rank: &'a [usize],
}

/// Maps world x-y into a square panel at (`left`, `top`) with equal scales, y up.
struct Frame {
    left: f64,
    top: f64,
    min: [f64; 2],
    scale: f64,
}

impl Frame {
    fn fit(points: impl Iterator<Item = [f64; 2]>, left: f64, top: f64) -> Self {
        let (mut min, mut max) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for p in points {
            for a in 0..2 {
                min[a] = min[a].min(p[a]);
                max[a] = max[a].max(p[a]);
            }
        }
        if !min[0].is_finite() {
            (min, max) = ([0.0; 2], [1.0; 2]);
        }
        let span = (max[0] - min[0]).max(max[1] - min[1]).max(1e-9);
        // Centre the shorter axis.
        let pad = |a: usize| (span - (max[a] - min[a])) / 2.0;
        Self {
            left,
            top,
            min: [min[0] - pad(0), min[1] - pad(1)],
            scale: PANEL / span,
        }
    }

    fn map(&self, p: [f64; 2]) -> (f64, f64) {
        (
            self.left + (p[0] - self.min[0]) * self.scale,
            self.top + PANEL - (p[1] - self.min[1]) * self.scale,
        )
    }
}

fn polyline(svg: &mut String, frame: &Frame, points: &[[f64; 2]], style: &str) {
    let mut path = String::new();
    for p in points {
        let (x, y) = frame.map(*p);
        let _ = write!(path, "{x:.1},{y:.1} ");
    }
    let _ = writeln!(
        svg,
        r#"<polyline fill="none" {style} points="{}"/>"#,
        path.trim_end()
    );
}

fn trajectory(svg: &mut String, drawn: &Drawn, view: View, left: f64, top: f64) {
    let project = |points: &[Option<[f64; 3]>]| -> (Vec<[f64; 2]>, Vec<[f64; 2]>) {
        let (path, dots) = split(points, drawn.landmark);
        let flat = |p: Vec<[f64; 3]>| p.iter().map(|p| view.project(p)).collect();
        (flat(path), flat(dots))
    };
    let ((before, _), (after, landmarks)) = (project(drawn.before), project(drawn.after));
    let frame = Frame::fit(
        before.iter().chain(&after).chain(&landmarks).copied(),
        left,
        top,
    );
    let _ = writeln!(
        svg,
        r##"<rect x="{left}" y="{top}" width="{PANEL}" height="{PANEL}" fill="none" stroke="#ccc"/>"##
    );
    axes(svg, &frame, view);
    polyline(
        svg,
        &frame,
        &before,
        &format!(r#"stroke="{INITIAL}" stroke-width="1""#),
    );
    let mut loops = 0;
    let mut path = String::new();
    for f in drawn.factors {
        let &[a, b] = f.variables() else { continue };
        if drawn.landmark[a] || drawn.landmark[b] || drawn.rank[a].abs_diff(drawn.rank[b]) == 1 {
            continue;
        }
        if let (Some(pa), Some(pb)) = (drawn.after[a], drawn.after[b]) {
            let (x1, y1) = frame.map(view.project(&pa));
            let (x2, y2) = frame.map(view.project(&pb));
            let _ = write!(path, "M{x1:.1},{y1:.1}L{x2:.1},{y2:.1}");
            loops += 1;
        }
    }
    if loops > 0 {
        let _ = writeln!(
            svg,
            r#"<path d="{path}" stroke="{LOOP}" stroke-opacity="0.25" stroke-width="0.6" fill="none"/>"#
        );
    }
    polyline(
        svg,
        &frame,
        &after,
        &format!(r#"stroke="{OPTIMUM}" stroke-width="1.2""#),
    );
    let mut dots = String::new();
    for p in &landmarks {
        let (x, y) = frame.map(*p);
        let _ = write!(dots, "M{x:.1},{y:.1}h0");
    }
    if !landmarks.is_empty() {
        let _ = writeln!(
            svg,
            r#"<path class="landmarks" d="{dots}" stroke="{LANDMARK}" stroke-width="3" stroke-linecap="round" fill="none"/>"#
        );
    }
    // View name, legend and scale bar.
    let _ = writeln!(
        svg,
        r##"<text x="{:.1}" y="{:.1}" text-anchor="end" fill="#666">{}</text>"##,
        left + PANEL - 6.0,
        top + 16.0,
        view.label
    );
    let y = top + PANEL + 20.0 + AXIS_ROOM;
    let _ = writeln!(
        svg,
        r#"<text x="{left}" y="{y}"><tspan fill="{INITIAL}">━ initial guess</tspan>  <tspan fill="{OPTIMUM}">━ optimum</tspan>  <tspan fill="{LOOP}">━ loop closures ({loops})</tspan>{}</text>"#,
        if landmarks.is_empty() {
            String::new()
        } else {
            format!(
                r#"  <tspan fill="{LANDMARK}">● landmarks ({})</tspan>"#,
                landmarks.len()
            )
        }
    );
    let metres = nice_length(PANEL / frame.scale / 5.0);
    let bar = metres * frame.scale;
    let (x0, y0) = (left + PANEL - bar - 10.0, top + PANEL - 12.0);
    let _ = writeln!(
        svg,
        r#"<path d="M{x0:.1},{y0:.1}h{bar:.1}" stroke="black" stroke-width="2"/><text x="{:.1}" y="{:.1}" text-anchor="middle">{} m</text>"#,
        x0 + bar / 2.0,
        y0 - 5.0,
        format_number(metres)
    );
}

/// Tick marks and labels on the panel's bottom (first axis) and left (second axis) edges, at
/// round values about a fifth of the panel apart, and the axes' names.
fn axes(svg: &mut String, frame: &Frame, view: View) {
    let span = PANEL / frame.scale;
    let step = nice_length(span / 5.0);
    let (left, top) = (frame.left, frame.top);
    let bottom = top + PANEL;
    for axis in 0..2 {
        let first = (frame.min[axis] / step).ceil() as i64;
        let last = ((frame.min[axis] + span) / step).floor() as i64;
        for k in first..=last {
            let value = k as f64 * step;
            let label = tick_label(value, step);
            if axis == 0 {
                let (x, _) = frame.map([value, frame.min[1]]);
                let _ = writeln!(
                    svg,
                    r##"<path d="M{x:.1},{bottom:.1}v5" stroke="#888"/><text x="{x:.1}" y="{:.1}" text-anchor="middle" font-size="11">{label}</text>"##,
                    bottom + 17.0
                );
            } else {
                let (_, y) = frame.map([frame.min[0], value]);
                let _ = writeln!(
                    svg,
                    r##"<path d="M{left:.1},{y:.1}h-5" stroke="#888"/><text x="{:.1}" y="{:.1}" text-anchor="end" font-size="11">{label}</text>"##,
                    left - 7.0,
                    y + 4.0
                );
            }
        }
    }
    let _ = writeln!(
        svg,
        r#"<text x="{:.1}" y="{:.1}" text-anchor="middle" font-size="12">{}</text>"#,
        left + PANEL / 2.0,
        bottom + 34.0,
        view.names[0]
    );
    let (x, y) = (left - 46.0, top + PANEL / 2.0);
    let _ = writeln!(
        svg,
        r#"<text x="{x:.1}" y="{y:.1}" text-anchor="middle" font-size="12" transform="rotate(-90 {x:.1} {y:.1})">{}</text>"#,
        view.names[1]
    );
}

/// A tick value with as many decimals as the tick step needs (0.5 → `2.5`, 20 → `40`).
fn tick_label(value: f64, step: f64) -> String {
    let decimals = (-step.log10().floor()).max(0.0) as usize;
    let text = format!("{value:.decimals$}");
    // `-0` reads as a mistake.
    if text
        .trim_start_matches('-')
        .chars()
        .all(|c| c == '0' || c == '.')
    {
        text.trim_start_matches('-').to_string()
    } else {
        text
    }
}

/// 1, 2 or 5 times a power of ten, at most `upper`.
fn nice_length(upper: f64) -> f64 {
    let power = 10f64.powf(upper.log10().floor());
    [5.0, 2.0, 1.0]
        .into_iter()
        .map(|m| m * power)
        .find(|&l| l <= upper)
        .unwrap_or(power)
}

fn format_number(x: f64) -> String {
    if x >= 1.0 {
        format!("{x:.0}")
    } else {
        format!("{x}")
    }
}

fn convergence(svg: &mut String, summary: &Summary, left: f64, top: f64) {
    // Iteration 0 is the initial cost; then each iteration's accepted cost.
    let mut costs = vec![(0usize, summary.initial_chi2, true)];
    for r in &summary.iteration_log {
        costs.push((r.iteration, r.chi2, true));
        if !r.accepted {
            costs.push((r.iteration, r.trial_chi2, false));
        }
    }
    let positive = costs.iter().filter(|c| c.1 > 0.0 && c.1.is_finite());
    let lo = positive.clone().map(|c| c.1).fold(f64::INFINITY, f64::min);
    let hi = positive.map(|c| c.1).fold(f64::NEG_INFINITY, f64::max);
    let (lo, hi) = if lo.is_finite() {
        (lo, hi)
    } else {
        (1.0, 10.0)
    };
    let (d0, d1) = (
        lo.log10().floor(),
        hi.log10().ceil().max(lo.log10().floor() + 1.0),
    );
    let last = costs.iter().map(|c| c.0).max().unwrap_or(0).max(1);
    let x = |i: usize| left + PANEL * i as f64 / last as f64;
    let y = |c: f64| top + PANEL - PANEL * (c.max(10f64.powf(d0)).log10() - d0) / (d1 - d0);
    let _ = writeln!(
        svg,
        r##"<rect x="{left}" y="{top}" width="{PANEL}" height="{PANEL}" fill="none" stroke="#ccc"/>"##
    );
    for d in d0 as i32..=d1 as i32 {
        let yy = y(10f64.powi(d));
        let _ = writeln!(
            svg,
            r##"<path d="M{left},{yy:.1}h{PANEL}" stroke="#eee"/><text x="{:.1}" y="{:.1}" text-anchor="end" font-size="11">1e{d}</text>"##,
            left - 4.0,
            yy + 4.0
        );
    }
    let mut path = String::new();
    for (i, c, accepted) in &costs {
        if *accepted {
            let _ = write!(
                path,
                "{}{:.1},{:.1}",
                if path.is_empty() { "M" } else { "L" },
                x(*i),
                y(*c)
            );
        }
    }
    let _ = writeln!(
        svg,
        r#"<path d="{path}" stroke="{OPTIMUM}" stroke-width="1.5" fill="none"/>"#
    );
    for (i, c, accepted) in &costs {
        let (fill, stroke) = if *accepted {
            (OPTIMUM, OPTIMUM)
        } else {
            ("white", LOOP)
        };
        let _ = writeln!(
            svg,
            r#"<circle cx="{:.1}" cy="{:.1}" r="3" fill="{fill}" stroke="{stroke}"/>"#,
            x(*i),
            y(*c)
        );
    }
    // Iteration ticks: every iteration up to ten, else round steps.
    let step = if last <= 10 {
        1
    } else {
        nice_length(last as f64 / 5.0).max(1.0) as usize
    };
    for i in (0..=last).step_by(step) {
        let _ = writeln!(
            svg,
            r##"<path d="M{:.1},{:.1}v5" stroke="#888"/><text x="{:.1}" y="{:.1}" text-anchor="middle" font-size="11">{i}</text>"##,
            x(i),
            top + PANEL,
            x(i),
            top + PANEL + 17.0
        );
    }
    let _ = writeln!(
        svg,
        r#"<text x="{:.1}" y="{:.1}" text-anchor="middle">iteration (0 = initial guess; hollow red: rejected trial)</text>"#,
        left + PANEL / 2.0,
        top + PANEL + 34.0
    );
    let _ = writeln!(
        svg,
        r#"<text x="{left}" y="{:.1}">cost χ² (log scale): {:.6e} → {:.6e} in {} iterations</text>"#,
        top - 8.0,
        summary.initial_chi2,
        summary.final_chi2,
        summary.iterations
    );
}

#[cfg(test)]
mod tests {
    use nalgebra::{DMatrix, Vector2};

    use super::*;
    use crate::factors::{BearingRangeSe2, BetweenSe2};
    use crate::geometry::{Point2, Se2};
    use crate::problem::Problem;

    /// Two poses and a landmark 10 m to the side whose id lies between theirs: pose ids skip
    /// (as Victoria Park's skip the ids its landmarks had), and 0 → 7 is still odometry.
    fn poses_and_a_landmark() -> Problem {
        let mut problem = Problem::new();
        problem
            .add_variable(0, Box::new(Se2::new(0.0, 0.0, 0.0)))
            .unwrap();
        problem
            .add_variable(5, Box::new(Point2(Vector2::new(0.5, 10.0))))
            .unwrap();
        problem
            .add_variable(7, Box::new(Se2::new(1.0, 0.0, 0.0)))
            .unwrap();
        let odometry = Box::new(BetweenSe2::new(0, 7, Se2::new(1.0, 0.0, 0.0)));
        problem
            .add_factor(odometry, &DMatrix::identity(3, 3), None, "odometry")
            .unwrap();
        let sighting = Box::new(BearingRangeSe2::from_body_position(0, 5, 0.5, 10.0));
        problem
            .add_factor(sighting, &DMatrix::identity(2, 2), None, "sighting")
            .unwrap();
        problem
    }

    #[test]
    fn landmarks_are_dots_and_not_points_of_the_trajectory_line() {
        let problem = poses_and_a_landmark();
        let values = &problem.values;
        let landmark: Vec<bool> = (0..values.len())
            .map(|v| is_landmark(values.variable(v)))
            .collect();
        assert_eq!(landmark, [false, true, false]);
        let (path, dots) = split(&positions(values), &landmark);
        assert_eq!(path, [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]);
        assert_eq!(dots, [[0.5, 10.0, 0.0]]);

        let all = positions(values);
        let rank = pose_ranks(values, &landmark);
        assert_eq!(rank, [0, usize::MAX, 1]);
        let drawn = Drawn {
            before: &all,
            after: &all,
            factors: problem.factors(),
            landmark: &landmark,
            rank: &rank,
        };
        let mut svg = String::new();
        trajectory(&mut svg, &drawn, View::TOP, 0.0, 0.0);
        let lines: Vec<&str> = svg.lines().filter(|l| l.contains("<polyline")).collect();
        assert_eq!(lines.len(), 2, "initial guess and optimum: {svg}");
        for line in lines {
            let points = line.split("points=\"").nth(1).unwrap();
            assert_eq!(
                points.split(' ').count(),
                2,
                "two poses, no landmark: {line}"
            );
        }
        let dots = svg
            .lines()
            .find(|l| l.contains(r#"class="landmarks""#))
            .expect("the landmark is drawn");
        assert_eq!(dots.matches('M').count(), 1, "{dots}");
        assert!(svg.contains("landmarks (1)"), "{svg}");
        assert!(
            svg.contains("loop closures (0)"),
            "a sighting is no loop closure, nor odometry over a skipped id: {svg}"
        );
    }
}
