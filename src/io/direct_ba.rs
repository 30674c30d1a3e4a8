//! The course's direct (photometric) bundle adjustment data: a directory with `poses.txt`
//! (one `time tx ty tz qx qy qz qw` line per image, T_cw), `points.txt` (`x y z` and the 16
//! intensities of the point's 4×4 patch, v fastest) and `0.png`, `1.png`, … (grayscale; RGB
//! with equal channels is accepted). Format details: `../shared/data/direct_ba/README.md`.
//!
//! Poses get keys 0..P, points P..P+N; one [`PhotometricPatch`] factor per (image, point) pair
//! whose patch is inside the image at the initial estimate. Pose 0 anchors the gauge (the
//! components' lowest key), the scale is left to LM's damping, and the points are eliminated
//! by Schur complement.

use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use nalgebra::{DMatrix, Quaternion, UnitQuaternion, Vector3};

use super::IoError;
use crate::factors::photometric_patch::PATCH_PIXELS;
use crate::factors::{Factor, PhotometricPatch, RobustKernel};
use crate::geometry::image::{GrayImage, Pinhole};
use crate::geometry::{Point3, Se3};
use crate::problem::{Key, Problem, Variable};

/// The intrinsics of the course's framework (`directBA.cpp`), for its 640×480 images.
pub const COURSE_CAMERA: Pinhole = Pinhole {
    fx: 277.34,
    fy: 291.402,
    cx: 312.234,
    cy: 239.777,
};

#[derive(Debug)]
pub struct DirectBaProblem {
    pub problem: Problem,
    pub images: Vec<Arc<GrayImage>>,
    pub camera: Pinhole,
    pub patches: Vec<[f64; PATCH_PIXELS]>,
    /// Points that no image sees at the initial estimate: loaded, not optimised.
    pub unseen_points: usize,
}

/// How well one image agrees with the patches of the points it sees.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct ImageAgreement {
    pub image: usize,
    pub points_visible: usize,
    /// Mean over visible points of the mean absolute difference (16 values) between the
    /// point's patch and the interpolated image, in gray levels.
    pub mean_abs_patch_difference: f64,
}

impl DirectBaProblem {
    pub fn num_poses(&self) -> usize {
        self.images.len()
    }

    pub fn num_points(&self) -> usize {
        self.patches.len()
    }

    pub fn pose_key(&self, i: usize) -> Key {
        i as Key
    }

    pub fn point_key(&self, j: usize) -> Key {
        (self.num_poses() + j) as Key
    }

    pub fn poses(&self) -> Vec<Se3> {
        (0..self.num_poses())
            .map(|i| {
                *self
                    .problem
                    .values
                    .get_as::<Se3>(self.pose_key(i))
                    .expect("pose keys hold poses")
            })
            .collect()
    }

    pub fn points(&self) -> Vec<Vector3<f64>> {
        (0..self.num_points())
            .map(|j| {
                self.problem
                    .values
                    .get_as::<Point3>(self.point_key(j))
                    .expect("point keys hold points")
                    .0
            })
            .collect()
    }

    /// Camera centres in the world, `−Rᵀ t` of each T_cw: the trajectory.
    pub fn camera_centres(&self) -> Vec<Vector3<f64>> {
        self.poses()
            .iter()
            .map(|t| -(t.rotation.inverse() * t.translation))
            .collect()
    }

    /// Per image, over the points whose patch is inside it at the current estimate.
    pub fn agreement(&self) -> Vec<ImageAgreement> {
        let poses = self.poses();
        let points = self.points();
        self.images
            .iter()
            .enumerate()
            .map(|(i, image)| {
                let (mut sum, mut visible) = (0.0, 0);
                for (patch, x) in self.patches.iter().zip(&points) {
                    let f = PhotometricPatch::new(0, 1, image.clone(), self.camera, *patch);
                    if f.visible_at(&poses[i], x).is_none() {
                        continue;
                    }
                    let mut e = [0.0f64; PATCH_PIXELS];
                    let point = Point3(*x);
                    let variables: [&dyn Variable; 2] = [&poses[i], &point];
                    f.evaluate(&variables, &mut e, None).expect("kinds match");
                    sum += e.iter().map(|v| v.abs()).sum::<f64>() / PATCH_PIXELS as f64;
                    visible += 1;
                }
                ImageAgreement {
                    image: i,
                    points_visible: visible,
                    mean_abs_patch_difference: if visible > 0 {
                        sum / visible as f64
                    } else {
                        f64::NAN
                    },
                }
            })
            .collect()
    }
}

fn invalid(file: &Path, reason: impl Into<String>) -> IoError {
    IoError::Invalid {
        file: file.to_path_buf(),
        reason: reason.into(),
    }
}

fn read_text(path: &Path) -> Result<String, IoError> {
    std::fs::read_to_string(path).map_err(|source| IoError::Read {
        file: path.to_path_buf(),
        source,
    })
}

/// Whitespace-separated numbers of one line, finite, exactly `count` of them.
fn numbers(path: &Path, line: usize, text: &str, count: usize) -> Result<Vec<f64>, IoError> {
    let parse_error = |reason: String| IoError::Parse {
        file: path.to_path_buf(),
        line,
        reason,
    };
    let values = text
        .split_whitespace()
        .enumerate()
        .map(|(k, token)| match token.parse::<f64>() {
            Ok(v) if v.is_finite() => Ok(v),
            Ok(_) => Err(parse_error(format!(
                "field {} is not finite: `{token}`",
                k + 1
            ))),
            Err(_) => Err(parse_error(format!(
                "field {} is not a number: `{token}`",
                k + 1
            ))),
        })
        .collect::<Result<Vec<_>, _>>()?;
    if values.len() != count {
        return Err(parse_error(format!(
            "expected {count} numbers, found {}",
            values.len()
        )));
    }
    Ok(values)
}

/// T_cw per line of `poses.txt`.
pub fn parse_poses(path: &Path, text: &str) -> Result<Vec<Se3>, IoError> {
    let mut poses = Vec::new();
    for (index, line) in super::without_bom(text).lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let v = numbers(path, index + 1, line, 8)?;
        let q = Quaternion::new(v[7], v[4], v[5], v[6]);
        if q.norm() < 1e-6 {
            return Err(IoError::Parse {
                file: path.to_path_buf(),
                line: index + 1,
                reason: "the quaternion is zero".into(),
            });
        }
        poses.push(Se3::new(
            UnitQuaternion::from_quaternion(q),
            Vector3::new(v[1], v[2], v[3]),
        ));
    }
    if poses.is_empty() {
        return Err(invalid(path, "no poses"));
    }
    Ok(poses)
}

/// A world point and its reference patch.
pub type PatchPoint = (Vector3<f64>, [f64; PATCH_PIXELS]);

/// (world point, patch) per line of `points.txt`.
pub fn parse_points(path: &Path, text: &str) -> Result<Vec<PatchPoint>, IoError> {
    let mut points = Vec::new();
    for (index, line) in super::without_bom(text).lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let v = numbers(path, index + 1, line, 3 + PATCH_PIXELS)?;
        let mut patch = [0.0; PATCH_PIXELS];
        patch.copy_from_slice(&v[3..]);
        points.push((Vector3::new(v[0], v[1], v[2]), patch));
    }
    if points.is_empty() {
        return Err(invalid(path, "no points"));
    }
    Ok(points)
}

/// An 8-bit PNG as intensities: gray as is; colour as 0.299 R + 0.587 G + 0.114 B (OpenCV's
/// grayscale read, equal to any channel when the channels are equal, as in the course's files).
pub fn load_gray_png(path: &Path) -> Result<GrayImage, IoError> {
    let file = File::open(path).map_err(|source| IoError::Read {
        file: path.to_path_buf(),
        source,
    })?;
    let mut decoder = png::Decoder::new(BufReader::new(file));
    decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let not_png = |e: png::DecodingError| invalid(path, format!("not a readable PNG: {e}"));
    let mut reader = decoder.read_info().map_err(not_png)?;
    let size = reader
        .output_buffer_size()
        .ok_or_else(|| invalid(path, "the image is too large"))?;
    let mut buffer = vec![0u8; size];
    let frame = reader.next_frame(&mut buffer).map_err(not_png)?;
    let (width, height) = (frame.width as usize, frame.height as usize);
    let channels = frame.color_type.samples();
    let bytes = &buffer[..frame.buffer_size()];
    let pixels = bytes
        .chunks_exact(channels)
        .map(|px| match channels {
            1 | 2 => f32::from(px[0]),
            _ => 0.299 * f32::from(px[0]) + 0.587 * f32::from(px[1]) + 0.114 * f32::from(px[2]),
        })
        .collect();
    GrayImage::new(width, height, pixels)
        .ok_or_else(|| invalid(path, "pixel count does not match the size"))
}

/// Loads `dir` (see the module documentation); `robust` goes on every factor.
pub fn load(
    dir: &Path,
    camera: Pinhole,
    robust: Option<RobustKernel>,
) -> Result<DirectBaProblem, IoError> {
    let poses_path = dir.join("poses.txt");
    let points_path = dir.join("points.txt");
    let poses = parse_poses(&poses_path, &read_text(&poses_path)?)?;
    let points = parse_points(&points_path, &read_text(&points_path)?)?;
    let images = (0..poses.len())
        .map(|i| load_gray_png(&dir.join(format!("{i}.png"))).map(Arc::new))
        .collect::<Result<Vec<_>, _>>()?;
    build(poses, points, images, camera, robust).map_err(|reason| IoError::Invalid {
        file: PathBuf::from(dir),
        reason,
    })
}

/// The problem from parsed parts (also used by tests with synthetic images).
pub fn build(
    poses: Vec<Se3>,
    points: Vec<PatchPoint>,
    images: Vec<Arc<GrayImage>>,
    camera: Pinhole,
    robust: Option<RobustKernel>,
) -> Result<DirectBaProblem, String> {
    if images.len() != poses.len() {
        return Err(format!("{} poses but {} images", poses.len(), images.len()));
    }
    let mut problem = Problem::new().eliminating(&["point3"]);
    for (i, pose) in poses.iter().enumerate() {
        problem
            .add_variable(i as Key, Box::new(*pose))
            .map_err(|e| e.to_string())?;
    }
    let information = DMatrix::identity(PATCH_PIXELS, PATCH_PIXELS);
    let mut unseen_points = 0;
    let mut patches = Vec::with_capacity(points.len());
    for (j, (x, patch)) in points.into_iter().enumerate() {
        let key = (poses.len() + j) as Key;
        problem
            .add_variable(key, Box::new(Point3(x)))
            .map_err(|e| e.to_string())?;
        let mut seen = false;
        for (i, image) in images.iter().enumerate() {
            let factor = PhotometricPatch::new(i as Key, key, image.clone(), camera, patch);
            if factor.visible_at(&poses[i], &x).is_some() {
                problem
                    .add_factor(
                        Box::new(factor),
                        &information,
                        robust,
                        format!("point {j} in image {i}"),
                    )
                    .map_err(|e| e.to_string())?;
                seen = true;
            }
        }
        if !seen {
            unseen_points += 1;
            problem.set_fixed(key, true).map_err(|e| e.to_string())?;
        }
        patches.push(patch);
    }
    Ok(DirectBaProblem {
        problem,
        images,
        camera,
        patches,
        unseen_points,
    })
}
