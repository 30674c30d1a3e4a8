//! From ROS messages to batches: odometry becomes keyframes (a new one when the robot has moved
//! `keyframe_distance` or turned `keyframe_angle` since the last) joined by `between_se3`
//! factors; an absolute pose becomes a `prior_se3` on the keyframe nearest in time.
//!
//! Noise. ROS covariances are 6×6 row-major over `[x y z rot_x rot_y rot_z]`, which is the
//! residual order of both `between_se3` and `prior_se3` (`[translation; Log(rotation)]`), so
//! the information is the covariance's inverse, unpermuted. For a relative factor the pose
//! covariance of the odometry message that closes the keyframe is taken as the covariance of
//! the motion since the previous keyframe (what wheel and visual odometry that publish a
//! per-step covariance mean); a source whose covariance grows without bound over time would
//! need differencing, which is not done. An all-zero covariance (unknown, as many drivers
//! publish) gets [`DEFAULT_ODOMETRY_SIGMAS`]; any other that is not positive definite refuses
//! the message.

use std::collections::{BTreeMap, HashSet};

use nalgebra::{Isometry3, Matrix6, Quaternion as NaQuaternion, Translation3, UnitQuaternion};

use super::bounds::{self, BadValue};
use super::messages::{Covariance, Odometry, Pose, PoseWithCovarianceStamped};
use super::robot_nodes::SharedKeyframes;
use crate::api::robots::robot_key;
use crate::api::ros2::Ros2Binding;
use crate::api::wire::{Batch, FactorSpec, VariableSpec};
use crate::variables::Key;

/// Sigmas `[x y z rot_x rot_y rot_z]` (m, rad) for odometry that publishes no covariance.
pub const DEFAULT_ODOMETRY_SIGMAS: [f64; 6] = [0.05, 0.05, 0.05, 0.01, 0.01, 0.01];

/// Sigmas of the weak prior that anchors the first keyframe when absolute priors are expected
/// (they, not the first odometry pose, should decide where the trajectory lies).
const ANCHOR_SIGMAS: [f64; 6] = [100.0, 100.0, 100.0, 3.0, 3.0, 3.0];

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MessageError {
    #[error("the {what} covariance is not symmetric positive definite")]
    Covariance { what: &'static str },
    #[error(transparent)]
    Value(#[from] BadValue),
    #[error("an absolute pose arrived before any keyframe: there is nothing to attach it to")]
    NoKeyframeYet,
    #[error("{field} {t:?} s has no keyframe within {tolerance} s (keyframe_tolerance); the nearest is at {nearest:?} s")]
    NoKeyframeNear {
        field: &'static str,
        t: f64,
        nearest: f64,
        tolerance: f64,
    },
    #[error("{held} loop closures and landmark sightings are held waiting for the odometry of their keyframes: no more")]
    TooManyAhead { held: usize },
    #[error("both stamps are nearest keyframe {key}: a loop closure joins two keyframes")]
    SameKeyframe { key: Key },
    #[error("{field} `{name}` is no robot of this binding (ros2.robots: a namespace or an id)")]
    UnknownRobot { field: &'static str, name: String },
    #[error("{held} IMU samples are held waiting for odometry to make a keyframe: no more")]
    TooManyHeld { held: usize },
}

struct Keyframe {
    key: Key,
    /// Where odometry put it, in odometry's frame.
    odometry_pose: Isometry3<f64>,
}

/// The binding's memory of the keyframes it has made (one per session binding).
pub struct Keyframer {
    distance: f64,
    angle: f64,
    /// Priors are expected: anchor the first keyframe weakly instead of fixing it.
    expects_priors: bool,
    last: Option<Keyframe>,
    next_key: Key,
    /// Keyframe keys by stamp (nanoseconds), for the nearest-in-time lookup of priors, loop
    /// closures and landmark sightings.
    pub(super) by_stamp: BTreeMap<i64, Key>,
    /// How far (seconds) a closure's or a sighting's stamp may be from its keyframe's.
    pub(super) tolerance: f64,
    /// The landmarks created so far (`closures`).
    pub(super) landmarks: HashSet<Key>,
    /// A robot's node: its robot (keys `robot_key(robot, i)`, the first keyframe free: the
    /// session anchors each robot's component itself) and the stamps every node shares.
    pub(super) robot: Option<(u8, SharedKeyframes)>,
}

impl Keyframer {
    pub fn new(binding: &Ros2Binding) -> Self {
        Self {
            distance: binding.keyframe_distance,
            angle: binding.keyframe_angle,
            expects_priors: binding.prior_topic.is_some(),
            last: None,
            next_key: 0,
            by_stamp: BTreeMap::new(),
            tolerance: binding.keyframe_tolerance,
            landmarks: HashSet::new(),
            robot: None,
        }
    }

    /// Robot `robot`'s keyframer in a node per robot: its keys from `robot_key(robot, 0)`, its
    /// keyframes' stamps shared with the other nodes (`keyframes`).
    pub fn for_robot(binding: &Ros2Binding, robot: u8, keyframes: SharedKeyframes) -> Self {
        Self {
            next_key: robot_key(robot as char, 0),
            robot: Some((robot, keyframes)),
            ..Self::new(binding)
        }
    }

    fn remember(&mut self, stamp_ns: i64, key: Key) {
        self.by_stamp.insert(stamp_ns, key);
        if let Some((robot, shared)) = &self.robot {
            shared.insert(*robot, stamp_ns, key);
        }
    }

    /// Continues a session that already holds keys up to `max_key` (after a restart of the
    /// service): new keyframes take the keys after it. What odometry said of the old keyframes
    /// is gone, so the first new one starts a segment of its own, weakly anchored at its
    /// odometry pose (never fixed: the old segment keeps the gauge).
    /// The stamps of the old keyframes are remembered (`keyframes`, from their variables):
    /// priors, closures and sightings still find them.
    pub fn resume_after(&mut self, max_key: Key, keyframes: impl IntoIterator<Item = (Key, f64)>) {
        self.next_key = max_key + 1;
        self.expects_priors = true;
        for (key, stamp) in keyframes {
            self.remember(stamp_ns(stamp), key);
        }
    }

    /// The batch a new keyframe makes, or `None` while the robot has not moved enough. The
    /// keyframer's state changes only when a batch is returned: the caller must apply it (a
    /// refused batch leaves a gap its next keyframe's factor would reach across).
    pub fn on_odometry(&mut self, odometry: &Odometry) -> Result<Option<Batch>, MessageError> {
        let pose = isometry(&odometry.pose.pose)?;
        let stamp = odometry.header.stamp.seconds();
        let key = self.next_key;
        let batch = match &self.last {
            None => self.first_keyframe(key, &pose, stamp),
            Some(last) => {
                if !has_moved(&last.odometry_pose, &pose, self.distance, self.angle) {
                    return Ok(None);
                }
                let motion = last.odometry_pose.inverse() * pose;
                let noise = information(&odometry.pose.covariance, "odometry")?
                    .map_or(Noise::Sigmas(DEFAULT_ODOMETRY_SIGMAS), |m| {
                        Noise::Information(m.iter().copied().collect())
                    });
                Batch {
                    // The value is predicted from the factor, i.e. from the optimised previous
                    // keyframe, not odometry's drifting frame.
                    variables: vec![variable(key, None, stamp)],
                    factors: vec![factor("between_se3", vec![last.key, key], &motion, noise)],
                    ..Batch::default()
                }
            }
        };
        self.last = Some(Keyframe {
            key,
            odometry_pose: pose,
        });
        self.next_key += 1;
        self.remember(stamp_ns(stamp), key);
        Ok(Some(batch))
    }

    /// The newest keyframe: its key and where odometry put it.
    pub fn last_keyframe(&self) -> Option<(Key, Isometry3<f64>)> {
        self.last.as_ref().map(|k| (k.key, k.odometry_pose))
    }

    fn first_keyframe(&self, key: Key, pose: &Isometry3<f64>, stamp: f64) -> Batch {
        let mut first = variable(key, Some(wire_pose(pose)), stamp);
        let mut factors = Vec::new();
        match (self.expects_priors, self.robot.is_some()) {
            (true, _) => factors.push(factor(
                "prior_se3",
                vec![key],
                pose,
                Noise::Sigmas(ANCHOR_SIGMAS),
            )),
            // A robot's component is anchored by the session (its gauge) and moved by merges.
            (false, true) => {}
            // The gauge: with odometry alone the first pose is where odometry says.
            (false, false) => first.fixed = true,
        }
        Batch {
            variables: vec![first],
            factors,
            ..Batch::default()
        }
    }

    /// A `prior_se3` on the keyframe nearest `prior`'s stamp.
    pub fn on_prior(&self, prior: &PoseWithCovarianceStamped) -> Result<Batch, MessageError> {
        let pose = isometry(&prior.pose.pose)?;
        let information = information(&prior.pose.covariance, "prior")?
            .ok_or(MessageError::Covariance { what: "prior" })?;
        let key = nearest_key(&self.by_stamp, stamp_ns(prior.header.stamp.seconds()))
            .ok_or(MessageError::NoKeyframeYet)?;
        Ok(Batch {
            factors: vec![factor(
                "prior_se3",
                vec![key],
                &pose,
                Noise::Information(information.iter().copied().collect()),
            )],
            ..Batch::default()
        })
    }
}

pub(super) fn stamp_ns(seconds: f64) -> i64 {
    (seconds * 1e9).round() as i64
}

/// Whether the robot, now at `pose`, has moved `distance` or turned `angle` since `from`.
pub(super) fn has_moved(
    from: &Isometry3<f64>,
    pose: &Isometry3<f64>,
    distance: f64,
    angle: f64,
) -> bool {
    let motion = from.inverse() * pose;
    motion.translation.vector.norm() >= distance || motion.rotation.angle() >= angle
}

/// The key whose stamp (ns) is nearest `at`; `None` when there are none.
pub(super) fn nearest_key(by_stamp: &BTreeMap<i64, Key>, at: i64) -> Option<Key> {
    nearest(by_stamp, at).map(|(key, _)| key)
}

/// The key whose stamp (ns) is nearest `at`, and that stamp.
pub(super) fn nearest(by_stamp: &BTreeMap<i64, Key>, at: i64) -> Option<(Key, i64)> {
    let before = by_stamp.range(..=at).next_back();
    let after = by_stamp.range(at..).next();
    let nearest = match (before, after) {
        (Some(b), Some(a)) => Some(if at - b.0 <= a.0 - at { b } else { a }),
        (b, a) => b.or(a),
    };
    nearest.map(|(&stamp, &key)| (key, stamp))
}

fn variable(key: Key, value: Option<Vec<f64>>, stamp: f64) -> VariableSpec {
    VariableSpec {
        key,
        kind: "se3".into(),
        value,
        fixed: false,
        stamp: Some(stamp),
    }
}

/// A factor's noise as the wire takes it: an information matrix, or sigmas (the server then
/// builds the diagonal information).
pub(super) enum Noise {
    /// Row-major, as `FactorSpec::information`.
    Information(Vec<f64>),
    Sigmas([f64; 6]),
}

pub(super) fn factor(
    kind: &str,
    keys: Vec<Key>,
    pose: &Isometry3<f64>,
    noise: Noise,
) -> FactorSpec {
    let (information, sigmas) = match noise {
        Noise::Information(m) => (Some(m), None),
        Noise::Sigmas(s) => (None, Some(s.to_vec())),
    };
    FactorSpec {
        factor_type: kind.into(),
        keys,
        measurement: wire_pose(pose),
        information,
        sigmas,
        robust: None,
        outlier: None,
    }
}

/// `se3` on the wire: `[x, y, z, qx, qy, qz, qw]`.
pub fn wire_pose(pose: &Isometry3<f64>) -> Vec<f64> {
    let t = pose.translation.vector;
    let q = pose.rotation.quaternion();
    vec![t.x, t.y, t.z, q.i, q.j, q.k, q.w]
}

/// The inverse of [`wire_pose`]; `None` for a value that is not seven numbers.
pub fn from_wire_pose(value: &[f64]) -> Option<Isometry3<f64>> {
    let [x, y, z, qx, qy, qz, qw] = value[..] else {
        return None;
    };
    Some(Isometry3::from_parts(
        Translation3::new(x, y, z),
        UnitQuaternion::from_quaternion(NaQuaternion::new(qw, qx, qy, qz)),
    ))
}

/// A ROS pose as an isometry: finite, within bounds, its quaternion unit within
/// [`bounds::UNIT_TOLERANCE`] (then normalised).
pub fn isometry(pose: &Pose) -> Result<Isometry3<f64>, MessageError> {
    bounds::pose(pose)?;
    let (p, o) = (pose.position, pose.orientation);
    Ok(Isometry3::from_parts(
        Translation3::new(p.x, p.y, p.z),
        UnitQuaternion::from_quaternion(NaQuaternion::new(o.w, o.x, o.y, o.z)),
    ))
}

/// The inverse of a ROS covariance (row-major; its order is our residual order); `None` when
/// it is all zeros (unknown).
pub(super) fn information(
    covariance: &Covariance,
    what: &'static str,
) -> Result<Option<Matrix6<f64>>, MessageError> {
    if covariance.0.iter().all(|&v| v == 0.0) {
        return Ok(None);
    }
    let refused = MessageError::Covariance { what };
    if !covariance.0.iter().all(|v| v.is_finite()) {
        return Err(refused);
    }
    // Symmetric: row-major and column-major read the same.
    let matrix = Matrix6::from_row_slice(&covariance.0);
    if (matrix - matrix.transpose()).abs().max() > 1e-9 * matrix.abs().max() {
        return Err(refused);
    }
    let inverse = matrix.cholesky().ok_or(refused)?.inverse();
    Ok(Some((inverse + inverse.transpose()) * 0.5))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transport::ros2::messages::{Header, Time};

    fn binding(priors: bool) -> Ros2Binding {
        let mut b: Ros2Binding =
            serde_json::from_str(r#"{"odometry_topic": "/odom", "keyframe_distance": 1.0}"#)
                .unwrap();
        if priors {
            b.prior_topic = Some("/gnss".into());
        }
        b
    }

    fn odometry(x: f64, yaw: f64, sec: i32) -> Odometry {
        let mut o = Odometry {
            header: Header {
                stamp: Time { sec, nanosec: 0 },
                frame_id: "odom".into(),
            },
            ..Default::default()
        };
        o.pose.pose.position.x = x;
        let q = UnitQuaternion::from_euler_angles(0.0, 0.0, yaw);
        o.pose.pose.orientation.z = q.k;
        o.pose.pose.orientation.w = q.w;
        for i in 0..6 {
            o.pose.covariance.0[i * 7] = if i < 3 { 0.04 } else { 0.0001 };
        }
        o
    }

    #[test]
    fn keyframes_start_fixed_and_follow_the_distance_and_angle_thresholds() {
        let mut k = Keyframer::new(&binding(false));
        let first = k.on_odometry(&odometry(0.0, 0.0, 1)).unwrap().unwrap();
        assert!(first.variables[0].fixed && first.factors.is_empty());
        assert_eq!(first.variables[0].stamp, Some(1.0));
        assert!(k.on_odometry(&odometry(0.5, 0.0, 2)).unwrap().is_none());
        let second = k.on_odometry(&odometry(1.2, 0.0, 3)).unwrap().unwrap();
        let f = &second.factors[0];
        assert_eq!(
            (f.factor_type.as_str(), f.keys.clone()),
            ("between_se3", vec![0, 1])
        );
        assert!((f.measurement[0] - 1.2).abs() < 1e-12);
        let info = f.information.as_ref().unwrap();
        assert!((info[0] - 25.0).abs() < 1e-9 && (info[35] - 10_000.0).abs() < 1e-6);
        // Turning in place past the angle threshold (0.2618 rad) is a keyframe too.
        assert!(k.on_odometry(&odometry(1.2, 0.3, 4)).unwrap().is_some());
    }

    #[test]
    fn priors_attach_to_the_nearest_keyframe_and_anchor_the_first_weakly() {
        let mut k = Keyframer::new(&binding(true));
        let prior = |sec| {
            let mut p = PoseWithCovarianceStamped::default();
            p.header.stamp = Time { sec, nanosec: 0 };
            p.pose.covariance = odometry(0.0, 0.0, 0).pose.covariance;
            p
        };
        assert_eq!(
            k.on_prior(&prior(1)).err(),
            Some(MessageError::NoKeyframeYet)
        );
        let first = k.on_odometry(&odometry(0.0, 0.0, 10)).unwrap().unwrap();
        assert!(!first.variables[0].fixed && first.factors[0].factor_type == "prior_se3");
        k.on_odometry(&odometry(2.0, 0.0, 20)).unwrap().unwrap();
        assert_eq!(k.on_prior(&prior(14)).unwrap().factors[0].keys, [0]);
        assert_eq!(k.on_prior(&prior(16)).unwrap().factors[0].keys, [1]);
        assert_eq!(k.on_prior(&prior(99)).unwrap().factors[0].keys, [1]);
    }

    #[test]
    fn a_resumed_binding_starts_after_the_existing_keys_unfixed() {
        let mut k = Keyframer::new(&binding(false));
        k.resume_after(41, []);
        let first = k.on_odometry(&odometry(0.0, 0.0, 1)).unwrap().unwrap();
        assert_eq!(first.variables[0].key, 42);
        assert!(!first.variables[0].fixed && first.factors[0].factor_type == "prior_se3");
    }

    #[test]
    fn bad_covariances_and_quaternions_are_refused() {
        let mut k = Keyframer::new(&binding(false));
        k.on_odometry(&odometry(0.0, 0.0, 1)).unwrap();
        let mut o = odometry(5.0, 0.0, 2);
        o.pose.covariance.0[0] = -1.0;
        assert!(matches!(
            k.on_odometry(&o),
            Err(MessageError::Covariance { .. })
        ));
        o = odometry(5.0, 0.0, 2);
        o.pose.pose.orientation.w = 2.0;
        assert!(matches!(
            k.on_odometry(&o),
            Err(MessageError::Value(BadValue::NotUnit { .. }))
        ));
        // Nothing was taken from the refused messages: the next keyframe is still key 1.
        let b = k.on_odometry(&odometry(5.0, 0.0, 3)).unwrap().unwrap();
        assert_eq!(b.variables[0].key, 1);
    }
}
