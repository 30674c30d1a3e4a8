//! `/tf` for a session with robots: `map → <robot>/odom` for every robot merged into the map,
//! so that each robot's own `odom → base_link` chain lands where the map has it.
//!
//! The transform is the robot's `map_from_odom` as `GET /v1/sessions/{s}/robots` reports it:
//! where the merge that brought it into the map put its odometry frame (identity for the robot
//! the map started with). A robot not merged yet has no place in the map, so nothing is
//! published for it (its component lives in a frame of its own, which `/tf` cannot relate to
//! `map`). The child frame id is the binding's `robot_odom_frame` (`robot_{robot}/odom` by
//! default: `robot_a/odom`).
//!
//! The transforms (one `TFMessage` with every merged robot's) go out after every solve and
//! every merge. Each is stamped with the robot's newest pose stamp (its values' `stamp`) plus
//! `transform_tolerance`, or with the wall clock plus the tolerance when its poses carry no
//! stamp; per robot, stamps strictly increase, as tf2 drops a transform whose stamp it holds.

use std::collections::BTreeMap;
use std::time::{SystemTime, UNIX_EPOCH};

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

use super::keyframes::from_wire_pose;
use super::messages::{Header, Time, Transform, TransformStamped};
use super::tf::TfBroadcaster;
use crate::api::robots::robot_of_key;
use crate::api::ros2::Ros2Binding;
use crate::api::wire::VariableValue;
use crate::api::ListRobots;
use crate::service::{Caller, Command, Recording, Reply, Service};

pub(super) struct RobotFrames {
    binding: Ros2Binding,
    tolerance_ns: i64,
    /// The stamp last published per robot.
    last_stamp_ns: BTreeMap<u8, i64>,
}

impl RobotFrames {
    pub fn new(binding: &Ros2Binding) -> Self {
        Self {
            binding: binding.clone(),
            tolerance_ns: (binding.transform_tolerance * 1e9).round() as i64,
            last_stamp_ns: BTreeMap::new(),
        }
    }

    /// Publishes `map → <robot>/odom` for every robot in the map; `estimate` (the whole
    /// session's, now) gives the robots' newest stamps.
    pub async fn publish(
        &mut self,
        tf: &TfBroadcaster,
        (service, caller, session): (&Service, &Caller, &str),
        estimate: &[VariableValue],
    ) {
        let command = Command::ListRobots(ListRobots {
            session: session.to_string(),
        });
        let report = match service.execute(caller, command, Recording::History).await {
            Ok(Reply::Robots(report)) => report,
            Ok(_) => return,
            Err(e) => {
                tracing::debug!(session, "no robots for /tf: {}", e.body.message);
                return;
            }
        };
        let mut newest: BTreeMap<u8, f64> = BTreeMap::new();
        for v in estimate {
            if let (Some(robot), Some(stamp)) = (robot_of_key(v.key), v.stamp) {
                let t = newest.entry(robot as u8).or_insert(stamp);
                *t = t.max(stamp);
            }
        }
        let now_ns = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as i64);
        let mut transforms = Vec::new();
        for robot in report.robots.iter().filter(|r| r.in_map) {
            let (Some(id), Some(map_from_odom)) = (
                robot.robot.bytes().next(),
                isometry_of(&robot.map_from_odom),
            ) else {
                continue;
            };
            let base_ns = newest
                .get(&id)
                .map_or(now_ns, |&s| Time::from_seconds(s).nanoseconds());
            let last = self.last_stamp_ns.get(&id).copied();
            let stamp_ns = (base_ns + self.tolerance_ns).max(last.map_or(i64::MIN, |l| l + 1));
            self.last_stamp_ns.insert(id, stamp_ns);
            transforms.push(TransformStamped {
                header: Header {
                    stamp: Time::from_nanoseconds(stamp_ns),
                    frame_id: self.binding.map_frame.clone(),
                },
                child_frame_id: self.binding.robot_odom_frame_of(id),
                transform: Transform::from(&map_from_odom),
            });
        }
        if !transforms.is_empty() {
            tf.put_transforms(transforms).await;
        }
    }
}

/// A robot's `map_from_odom` (`[x, y, z, qx, qy, qz, qw]`, or planar `[x, y, θ]`) as an
/// isometry.
fn isometry_of(wire: &[f64]) -> Option<Isometry3<f64>> {
    match *wire {
        [x, y, theta] => Some(Isometry3::from_parts(
            Translation3::new(x, y, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), theta),
        )),
        _ => from_wire_pose(wire),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn planar_and_spatial_frames_become_isometries() {
        let planar = isometry_of(&[1.0, 2.0, std::f64::consts::FRAC_PI_2]).unwrap();
        let p = planar * nalgebra::Point3::new(1.0, 0.0, 0.0);
        assert!((p - nalgebra::Point3::new(1.0, 3.0, 0.0)).norm() < 1e-12);
        let spatial = isometry_of(&[1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0]).unwrap();
        assert_eq!(spatial.translation.vector, Vector3::new(1.0, 2.0, 3.0));
        assert!(isometry_of(&[1.0]).is_none());
    }
}
