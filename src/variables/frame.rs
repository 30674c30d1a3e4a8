//! A robot's odometry frame as it sits in the map: a rigid transform, planar or spatial, that
//! moves the robot's values (poses, landmarks it placed) into the map frame; and the transform
//! one inter-robot closure implies between two components' frames.
//!
//! A closure `z` between pose `a` of component A and pose `b` of component B says where `b`
//! is seen from `a`. With A's estimate `x_a` (in A's frame) the closure predicts `b` in A's
//! frame, `x̂_b = x_a ∘ z` (the factor's own prediction, so any factor that can predict its far
//! end serves); B holds `x_b` in its own frame, so the frame transform the closure implies is
//! `T = x̂_b ∘ x_b⁻¹` (A's frame from B's): `T ∘ x_b = x̂_b`.

use nalgebra::{UnitQuaternion, Vector3};

use super::Variable;
use crate::geometry::{Point2, Point3, Se2, Se3};

/// A rigid transform between two frames (`to ← from`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Frame {
    Planar(Se2),
    Spatial(Se3),
}

impl Frame {
    /// The transform that takes `from` (a pose in the old frame) to `to` (the same pose in the
    /// new frame): `to ∘ from⁻¹`. `None` unless both are poses of one kind.
    pub fn between_poses(to: &dyn Variable, from: &dyn Variable) -> Option<Frame> {
        if let (Some(to), Some(from)) = (downcast::<Se2>(to), downcast::<Se2>(from)) {
            return Some(Frame::Planar(to.compose(&from.inverse())));
        }
        if let (Some(to), Some(from)) = (downcast::<Se3>(to), downcast::<Se3>(from)) {
            return Some(Frame::Spatial(to.compose(&from.inverse())));
        }
        None
    }

    /// `self ∘ other`; `None` when one is planar and the other spatial.
    pub fn compose(&self, other: &Frame) -> Option<Frame> {
        match (self, other) {
            (Frame::Planar(a), Frame::Planar(b)) => Some(Frame::Planar(a.compose(b))),
            (Frame::Spatial(a), Frame::Spatial(b)) => Some(Frame::Spatial(a.compose(b))),
            _ => None,
        }
    }

    pub fn inverse(&self) -> Frame {
        match self {
            Frame::Planar(a) => Frame::Planar(a.inverse()),
            Frame::Spatial(a) => Frame::Spatial(a.inverse()),
        }
    }

    /// Moves `v` into the new frame: a pose is composed on the left, a point transformed;
    /// returns `false` for a kind a frame does not move (or of the other dimension).
    pub fn apply(&self, v: &mut dyn Variable) -> bool {
        let any = v.as_any();
        let moved: Option<Box<dyn Variable>> = match self {
            Frame::Planar(t) => {
                if let Some(p) = any.downcast_ref::<Se2>() {
                    Some(Box::new(t.compose(p)))
                } else {
                    any.downcast_ref::<Point2>().map(|p| {
                        let (s, c) = t.theta.sin_cos();
                        let (x, y) = (p.0.x, p.0.y);
                        Box::new(Point2(nalgebra::Vector2::new(
                            t.x + c * x - s * y,
                            t.y + s * x + c * y,
                        ))) as Box<dyn Variable>
                    })
                }
            }
            Frame::Spatial(t) => {
                if let Some(p) = any.downcast_ref::<Se3>() {
                    Some(Box::new(t.compose(p)))
                } else {
                    any.downcast_ref::<Point3>().map(|p| {
                        Box::new(Point3(t.rotation * p.0 + t.translation)) as Box<dyn Variable>
                    })
                }
            }
        };
        match moved {
            Some(m) => v.assign_from(m.as_ref()),
            None => false,
        }
    }

    #[cfg(test)]
    /// How far apart two transforms are: (translation distance, rotation angle in radians).
    pub fn distance(&self, other: &Frame) -> Option<(f64, f64)> {
        match (self, other) {
            (Frame::Planar(a), Frame::Planar(b)) => {
                let d = a.between(b);
                Some((d.x.hypot(d.y), d.theta.abs()))
            }
            (Frame::Spatial(a), Frame::Spatial(b)) => {
                let d = a.between(b);
                Some((d.translation.norm(), d.rotation.angle()))
            }
            _ => None,
        }
    }

    /// The mean of transforms that agree closely (a consensus set): each is expressed relative
    /// to the first, averaged in the tangent space, and composed back. `None` when empty or
    /// mixed.
    pub fn mean(frames: &[Frame]) -> Option<Frame> {
        let first = *frames.first()?;
        let n = frames.len() as f64;
        match first {
            Frame::Planar(base) => {
                let mut sum = [0.0; 3];
                for f in frames {
                    let Frame::Planar(t) = f else { return None };
                    let d = base.between(t).log();
                    (0..3).for_each(|i| sum[i] += d[i] / n);
                }
                Some(Frame::Planar(base.compose(&Se2::exp(sum))))
            }
            Frame::Spatial(base) => {
                let mut sum = nalgebra::Vector6::zeros();
                for f in frames {
                    let Frame::Spatial(t) = f else { return None };
                    sum += base.between(t).log() / n;
                }
                Some(Frame::Spatial(base.compose(&Se3::exp(&sum))))
            }
        }
    }

    /// The transform as the wire shows it: `[x, y, θ]` or `[x, y, z, qx, qy, qz, qw]`.
    pub fn to_wire(self) -> Vec<f64> {
        match self {
            Frame::Planar(t) => t.to_array().to_vec(),
            Frame::Spatial(t) => {
                let q = t.rotation.quaternion();
                vec![
                    t.translation.x,
                    t.translation.y,
                    t.translation.z,
                    q.i,
                    q.j,
                    q.k,
                    q.w,
                ]
            }
        }
    }

    /// Reads [`Frame::to_wire`]'s form back (a journal's merge record).
    pub fn from_wire(v: &[f64]) -> Option<Frame> {
        match *v {
            [x, y, theta] => Some(Frame::Planar(Se2::new(x, y, theta))),
            [x, y, z, qx, qy, qz, qw] => {
                let q = nalgebra::Quaternion::new(qw, qx, qy, qz);
                (q.norm() > 0.5).then(|| {
                    Frame::Spatial(Se3::new(
                        UnitQuaternion::from_quaternion(q),
                        Vector3::new(x, y, z),
                    ))
                })
            }
            _ => None,
        }
        .filter(|f| f.to_wire().iter().all(|x| x.is_finite()))
    }
}

fn downcast<T: 'static>(v: &dyn Variable) -> Option<&T> {
    v.as_any().downcast_ref::<T>()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_frame_moves_poses_and_points_and_undoes_itself() {
        let t = Frame::Planar(Se2::new(1.0, 2.0, 0.5));
        let mut pose = Se2::new(3.0, -1.0, 0.2);
        assert!(t.apply(&mut pose));
        assert!(t.inverse().apply(&mut pose));
        let back = pose.to_array();
        for (a, b) in back.iter().zip([3.0, -1.0, 0.2]) {
            assert!((a - b).abs() < 1e-12, "{back:?}");
        }
        // A point goes where the pose with that origin goes.
        let mut point = Point2(nalgebra::Vector2::new(3.0, -1.0));
        let mut as_pose = Se2::new(3.0, -1.0, 0.0);
        assert!(t.apply(&mut point) && t.apply(&mut as_pose));
        assert!((point.0.x - as_pose.x).abs() < 1e-12 && (point.0.y - as_pose.y).abs() < 1e-12);
        // A spatial frame does not move a planar pose.
        assert!(!Frame::Spatial(Se3::identity()).apply(&mut pose));
    }

    #[test]
    fn the_transform_between_two_placements_of_a_pose_maps_one_onto_the_other() {
        let from = Se3::new(
            UnitQuaternion::from_euler_angles(0.1, -0.2, 0.7),
            Vector3::new(1.0, 2.0, 3.0),
        );
        let to = Se3::new(
            UnitQuaternion::from_euler_angles(-0.3, 0.2, 2.0),
            Vector3::new(-4.0, 0.5, 1.0),
        );
        let t = Frame::between_poses(&to, &from).unwrap();
        let mut moved = from;
        assert!(t.apply(&mut moved));
        let (dt, dr) = Frame::Spatial(moved).distance(&Frame::Spatial(to)).unwrap();
        assert!(dt < 1e-12 && dr < 1e-12, "{dt} {dr}");
        let wire = t.to_wire();
        let (dt, dr) = Frame::from_wire(&wire).unwrap().distance(&t).unwrap();
        assert!(dt < 1e-12 && dr < 1e-9);
    }

    #[test]
    fn the_mean_of_agreeing_transforms_lies_between_them() {
        let a = Frame::Planar(Se2::new(1.0, 0.0, 0.10));
        let b = Frame::Planar(Se2::new(1.2, 0.0, 0.14));
        let Some(Frame::Planar(m)) = Frame::mean(&[a, b]) else {
            panic!("planar");
        };
        assert!((m.theta - 0.12).abs() < 1e-9, "{m:?}");
        assert!(m.x > 1.0 && m.x < 1.2, "{m:?}");
    }
}
