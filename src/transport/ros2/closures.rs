//! A SLAM front-end's loop closures and landmark sightings (`factord_msgs`), attached to the
//! keyframes the [`Keyframer`] made from odometry, by stamp.
//!
//! - A loop closure becomes a `between_se3` factor between the keyframes nearest its
//!   `from_stamp` and `to_stamp`, each within the binding's `keyframe_tolerance`; its
//!   information is the inverse of its covariance (6×6 over `[x y z rot_x rot_y rot_z]`, the
//!   factor's residual order), which must be positive definite (unlike odometry, no default:
//!   a closure's weight is what decides whether it bends the map).
//! - `may_be_wrong`: the factor is sent with `"outlier": "auto"`: the session holds it out of
//!   the estimate until it finds it consistent with the map (docs/guide/wrong-closures.md).
//! - A landmark sighting becomes a `position_se3_point3` factor (the landmark's position in the
//!   body frame: what stereo, RGB-D, lidar features and tag detectors give) between the
//!   keyframe nearest its stamp and the `point3` landmark `('l' << 56) | landmark_id`, created
//!   with its first sighting (its value predicted from it: `t + R z`).

use nalgebra::{Isometry3, Matrix3, Matrix6};

use super::keyframes::{
    factor, information, isometry, nearest, stamp_ns, Keyframer, MessageError, Noise,
};
use super::messages::{LandmarkSighting, LoopClosure, Time};
use crate::api::outliers::OutlierMark;
use crate::api::wire::{Batch, FactorSpec, VariableSpec};
use crate::variables::Key;

/// The key of landmark `id` (GTSAM's `Symbol('l', id)`, as `io::gtsam_text` writes them).
pub fn landmark_key(id: u64) -> Key {
    (u64::from(b'l') << 56) | id
}

/// Whether `key` is a landmark's (keyframes count up from 0).
pub fn is_landmark(key: Key) -> bool {
    key >> 56 == u64::from(b'l')
}

impl Keyframer {
    /// A `between_se3` factor from the keyframe nearest `from_stamp` to the one nearest
    /// `to_stamp`.
    pub fn on_loop_closure(&self, closure: &LoopClosure) -> Result<Batch, MessageError> {
        let measurement = Measurement::of(closure)?;
        let from = self.keyframe_near(closure.from_stamp, "from_stamp")?;
        let to = self.keyframe_near(closure.to_stamp, "to_stamp")?;
        measurement.between(from, to)
    }

    /// A closure between robots, taken by the node of the robot it ends at: a `between_se3`
    /// factor from robot `from_robot`'s keyframe nearest `from_stamp` (in the stamps every
    /// robot's node shares) to this robot's nearest `to_stamp`.
    pub fn on_robot_loop_closure(
        &self,
        from_robot: u8,
        closure: &LoopClosure,
    ) -> Result<Batch, MessageError> {
        let measurement = Measurement::of(closure)?;
        let at = closure.from_stamp;
        let found = self
            .robot
            .as_ref()
            .and_then(|(_, shared)| shared.nearest(from_robot, stamp_ns(at.seconds())));
        let from = within(found, at, "from_stamp", self.tolerance)?;
        let to = self.keyframe_near(closure.to_stamp, "to_stamp")?;
        measurement.between(from, to)
    }

    /// A `position_se3_point3` factor on the keyframe nearest the sighting's stamp, and the
    /// landmark's variable at its first sighting. The landmark counts as known once the batch
    /// is returned (the caller applies it).
    pub fn on_landmark(&mut self, sighting: &LandmarkSighting) -> Result<Batch, MessageError> {
        let information = information3(&sighting.covariance)?;
        let pose = self.keyframe_near(sighting.header.stamp, "header.stamp")?;
        let landmark = landmark_key(sighting.landmark_id);
        let p = sighting.position;
        let variables = match self.landmarks.insert(landmark) {
            true => vec![VariableSpec {
                key: landmark,
                kind: "point3".into(),
                value: None,
                fixed: false,
                stamp: None,
            }],
            false => Vec::new(),
        };
        Ok(Batch {
            variables,
            factors: vec![FactorSpec {
                factor_type: "position_se3_point3".into(),
                keys: vec![pose, landmark],
                measurement: vec![p.x, p.y, p.z],
                information: Some(information.iter().copied().collect()),
                sigmas: None,
                robust: None,
                outlier: None,
            }],
            ..Batch::default()
        })
    }

    /// The keyframe whose stamp is nearest `at`, if within the tolerance.
    fn keyframe_near(&self, at: Time, field: &'static str) -> Result<Key, MessageError> {
        let found = nearest(&self.by_stamp, stamp_ns(at.seconds()));
        within(found, at, field, self.tolerance)
    }

    /// Landmarks the session already has (after a restart): their next sightings add no
    /// variable.
    pub fn resume_landmarks(&mut self, keys: impl IntoIterator<Item = Key>) {
        self.landmarks.extend(keys);
    }
}

/// `found`, the keyframe nearest `at` and its stamp, if within `tolerance` seconds of it.
fn within(
    found: Option<(Key, i64)>,
    at: Time,
    field: &'static str,
    tolerance: f64,
) -> Result<Key, MessageError> {
    let t = at.seconds();
    let (key, stamp) = found.ok_or(MessageError::NoKeyframeYet)?;
    let off = (stamp - stamp_ns(t)).abs() as f64 * 1e-9;
    if off > tolerance {
        return Err(MessageError::NoKeyframeNear {
            field,
            t,
            nearest: stamp as f64 * 1e-9,
            tolerance,
        });
    }
    Ok(key)
}

/// A closure's relative pose and information, checked before its keyframes are looked for.
struct Measurement {
    relative: Isometry3<f64>,
    information: Matrix6<f64>,
    may_be_wrong: bool,
}

impl Measurement {
    fn of(closure: &LoopClosure) -> Result<Self, MessageError> {
        let relative = isometry(&closure.relative_pose)?;
        let what = "loop closure";
        let information =
            information(&closure.covariance, what)?.ok_or(MessageError::Covariance { what })?;
        Ok(Self {
            relative,
            information,
            may_be_wrong: closure.may_be_wrong,
        })
    }

    fn between(&self, from: Key, to: Key) -> Result<Batch, MessageError> {
        if from == to {
            return Err(MessageError::SameKeyframe { key: from });
        }
        let mut factor = factor(
            "between_se3",
            vec![from, to],
            &self.relative,
            Noise::Information(self.information.iter().copied().collect()),
        );
        if self.may_be_wrong {
            factor.outlier = Some(OutlierMark::Auto);
        }
        Ok(Batch {
            factors: vec![factor],
            ..Batch::default()
        })
    }
}

/// The inverse of a sighting's 3×3 covariance (row-major), which must be symmetric positive
/// definite.
fn information3(covariance: &[f64; 9]) -> Result<Matrix3<f64>, MessageError> {
    let refused = MessageError::Covariance {
        what: "landmark sighting",
    };
    if !covariance.iter().all(|v| v.is_finite()) {
        return Err(refused);
    }
    let matrix = Matrix3::from_row_slice(covariance);
    if (matrix - matrix.transpose()).abs().max() > 1e-9 * matrix.abs().max() {
        return Err(refused);
    }
    let inverse = matrix.cholesky().ok_or(refused)?.inverse();
    Ok((inverse + inverse.transpose()) * 0.5)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::api::ros2::Ros2Binding;
    use crate::transport::ros2::messages::{Header, Odometry};

    fn keyframer() -> Keyframer {
        let b: Ros2Binding = serde_json::from_str(
            r#"{"odometry_topic": "/odom", "keyframe_distance": 1.0, "keyframe_tolerance": 0.05}"#,
        )
        .unwrap();
        let mut k = Keyframer::new(&b);
        for (i, x) in [0.0, 2.0, 4.0].into_iter().enumerate() {
            let mut o = Odometry {
                header: Header {
                    stamp: Time {
                        sec: 10 * (i as i32 + 1),
                        nanosec: 0,
                    },
                    frame_id: "odom".into(),
                },
                ..Default::default()
            };
            o.pose.pose.position.x = x;
            k.on_odometry(&o).unwrap().unwrap();
        }
        k
    }

    fn closure(from: Time, to: Time) -> LoopClosure {
        let mut c = LoopClosure {
            from_stamp: from,
            to_stamp: to,
            ..Default::default()
        };
        c.relative_pose.position.x = 4.0;
        for i in 0..6 {
            c.covariance.0[i * 7] = 0.01;
        }
        c
    }

    fn at(sec: i32, nanosec: u32) -> Time {
        Time { sec, nanosec }
    }

    #[test]
    fn a_closure_joins_the_keyframes_nearest_its_stamps_within_the_tolerance() {
        let k = keyframer();
        let b = k
            .on_loop_closure(&closure(at(10, 0), at(29, 960_000_000)))
            .unwrap();
        let f = &b.factors[0];
        assert_eq!(
            (f.factor_type.as_str(), &f.keys[..]),
            ("between_se3", &[0, 2][..])
        );
        assert!((f.information.as_ref().unwrap()[0] - 100.0).abs() < 1e-9);
        assert!(f.robust.is_none());
        let mut unsure = closure(at(10, 0), at(30, 0));
        unsure.may_be_wrong = true;
        let b = k.on_loop_closure(&unsure).unwrap();
        assert_eq!(b.factors[0].outlier, Some(OutlierMark::Auto));
        assert!(b.factors[0].robust.is_none());
        assert!(matches!(
            k.on_loop_closure(&closure(at(10, 0), at(29, 900_000_000))),
            Err(MessageError::NoKeyframeNear {
                field: "to_stamp",
                ..
            })
        ));
        assert_eq!(
            k.on_loop_closure(&closure(at(10, 0), at(10, 10))).err(),
            Some(MessageError::SameKeyframe { key: 0 })
        );
        let mut flat = closure(at(10, 0), at(30, 0));
        flat.covariance.0 = [0.0; 36];
        assert!(matches!(
            k.on_loop_closure(&flat),
            Err(MessageError::Covariance { .. })
        ));
    }

    #[test]
    fn a_closure_between_robots_finds_the_other_robots_keyframe_in_the_shared_stamps() {
        use crate::api::robots::robot_key;
        use crate::transport::ros2::robot_nodes::SharedKeyframes;
        let b: Ros2Binding = serde_json::from_str(
            r#"{"odometry_topic": "odom", "keyframe_distance": 1.0, "keyframe_tolerance": 0.05}"#,
        )
        .unwrap();
        let shared = SharedKeyframes::default();
        let mut robots = [b'a', b'b'].map(|r| Keyframer::for_robot(&b, r, shared.clone()));
        for (i, x) in [0.0, 2.0, 4.0].into_iter().enumerate() {
            for (r, k) in robots.iter_mut().enumerate() {
                let mut o = Odometry {
                    header: Header {
                        stamp: at(10 * (i as i32 + 1) + r as i32, 0),
                        frame_id: "odom".into(),
                    },
                    ..Default::default()
                };
                o.pose.pose.position.x = x;
                let batch = k.on_odometry(&o).unwrap().unwrap();
                // A robot's first keyframe is not fixed: the session anchors its component.
                assert!(!batch.variables[0].fixed && batch.factors.len() == (i > 0) as usize);
            }
        }
        // a's keyframe at 20 s to b's at 31 s, taken by b's node.
        let batch = robots[1]
            .on_robot_loop_closure(b'a', &closure(at(20, 0), at(31, 0)))
            .unwrap();
        assert_eq!(
            batch.factors[0].keys,
            [robot_key('a', 1), robot_key('b', 2)]
        );
        assert!(matches!(
            robots[1].on_robot_loop_closure(b'a', &closure(at(25, 0), at(31, 0))),
            Err(MessageError::NoKeyframeNear {
                field: "from_stamp",
                ..
            })
        ));
        assert_eq!(
            robots[1]
                .on_robot_loop_closure(b'c', &closure(at(20, 0), at(31, 0)))
                .err(),
            Some(MessageError::NoKeyframeYet)
        );
    }

    #[test]
    fn a_landmark_is_created_at_its_first_sighting_only() {
        let mut k = keyframer();
        let mut s = LandmarkSighting {
            landmark_id: 3,
            covariance: [0.04, 0.0, 0.0, 0.0, 0.04, 0.0, 0.0, 0.0, 0.04],
            ..Default::default()
        };
        s.header.stamp = at(20, 0);
        s.position.y = 1.5;
        let first = k.on_landmark(&s).unwrap();
        let key = landmark_key(3);
        assert!(is_landmark(key) && !is_landmark(41));
        assert_eq!(first.variables[0].key, key);
        assert_eq!(first.factors[0].keys, [1, key]);
        assert_eq!(first.factors[0].measurement, [0.0, 1.5, 0.0]);
        s.header.stamp = at(30, 0);
        let again = k.on_landmark(&s).unwrap();
        assert!(again.variables.is_empty() && again.factors[0].keys == [2, key]);
        s.covariance[0] = -1.0;
        assert!(matches!(
            k.on_landmark(&s),
            Err(MessageError::Covariance { .. })
        ));
    }
}
