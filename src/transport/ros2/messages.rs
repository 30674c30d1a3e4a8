//! The ROS 2 messages the binding reads and writes, as serde structs in the field order of their
//! `.msg` definitions (CDR is that order, nothing else), with the names and type hashes rmw_zenoh
//! puts in key expressions.
//!
//! Type hashes are the RIHS01 hashes of the Jazzy definitions (the same in Kilted and Rolling:
//! these messages have not changed since hashes were introduced in Iron). Source: computed as
//! rosidl does by `rosbags` 0.11.9 (`get_typestore(Stores.ROS2_JAZZY).hash_rihs01(name)`) and
//! checked against the hashes in rosidl-generated type-support sources (`nav_msgs` and
//! `geometry_msgs` `*__type_support.c`, `TYPE_HASH`) and, for `tf2_msgs/TFMessage`, against
//! the golden hash in rosidl's own tests.

use nalgebra::{Isometry3, UnitQuaternion};
use serde::de::{Error as _, SeqAccess, Visitor};
use serde::ser::SerializeTuple;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

use std::sync::LazyLock;

use super::cdr_codec::name_string;
use super::type_hash;

/// A ROS 2 message type as rmw_zenoh names it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RosType {
    /// The ROS name, `nav_msgs/msg/Odometry`.
    pub name: &'static str,
    /// The DDS-mangled name rmw_zenoh puts in key expressions, `nav_msgs::msg::dds_::Odometry_`.
    pub dds_name: &'static str,
    /// `RIHS01_<sha256 of the type description>`.
    pub hash: &'static str,
}

pub const ODOMETRY: RosType = RosType {
    name: "nav_msgs/msg/Odometry",
    dds_name: "nav_msgs::msg::dds_::Odometry_",
    hash: "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
};

pub const POSE_WITH_COVARIANCE_STAMPED: RosType = RosType {
    name: "geometry_msgs/msg/PoseWithCovarianceStamped",
    dds_name: "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_",
    hash: "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e",
};

pub const IMU: RosType = RosType {
    name: "sensor_msgs/msg/Imu",
    dds_name: "sensor_msgs::msg::dds_::Imu_",
    hash: "RIHS01_7d9a00ff131080897a5ec7e26e315954b8eae3353c3f995c55faf71574000b5b",
};

pub const TF_MESSAGE: RosType = RosType {
    name: "tf2_msgs/msg/TFMessage",
    dds_name: "tf2_msgs::msg::dds_::TFMessage_",
    hash: "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
};

pub const PATH: RosType = RosType {
    name: "nav_msgs/msg/Path",
    dds_name: "nav_msgs::msg::dds_::Path_",
    hash: "RIHS01_1957a5bb3cee5da65c4e52e52b65a93df227efce4c20f8458b36e73066ca334b",
};

/// The graph as rviz and Foxglove draw it. Its hash as `rosbags` computes it from the Jazzy
/// definitions, and recomputed from them by `type_hash`.
pub const MARKER_ARRAY: RosType = RosType {
    name: "visualization_msgs/msg/MarkerArray",
    dds_name: "visualization_msgs::msg::dds_::MarkerArray_",
    hash: "RIHS01_86cb8800b6fb05b5eff1abd7a56f62a5641d3ae9a1c29e78e67e704f1d067dcf",
};

/// `factord_msgs/msg/LoopClosure` (`clients/ros2/factord_msgs`).
pub static LOOP_CLOSURE: LazyLock<RosType> = LazyLock::new(|| {
    ours(
        "factord_msgs/msg/LoopClosure",
        "factord_msgs::msg::dds_::LoopClosure_",
    )
});

/// `factord_msgs/msg/RobotLoopClosure` (`clients/ros2/factord_msgs`).
pub static ROBOT_LOOP_CLOSURE: LazyLock<RosType> = LazyLock::new(|| {
    ours(
        "factord_msgs/msg/RobotLoopClosure",
        "factord_msgs::msg::dds_::RobotLoopClosure_",
    )
});

/// `factord_msgs/msg/LandmarkSighting` (`clients/ros2/factord_msgs`).
pub static LANDMARK_SIGHTING: LazyLock<RosType> = LazyLock::new(|| {
    ours(
        "factord_msgs/msg/LandmarkSighting",
        "factord_msgs::msg::dds_::LandmarkSighting_",
    )
});

/// One of our own types, its hash computed from its `.msg` file (once, kept for the process).
fn ours(name: &'static str, dds_name: &'static str) -> RosType {
    let definitions: Vec<_> = type_hash::STANDARD
        .iter()
        .chain(type_hash::FACTORD_MSGS)
        .copied()
        .collect();
    let hash = type_hash::rihs01(name, &definitions)
        .expect("factord_msgs refer only to known types (type_hash's tests)");
    RosType {
        name,
        dds_name,
        hash: hash.leak(),
    }
}

/// `builtin_interfaces/Time`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    pub fn seconds(self) -> f64 {
        f64::from(self.sec) + f64::from(self.nanosec) * 1e-9
    }

    pub fn nanoseconds(self) -> i64 {
        i64::from(self.sec) * 1_000_000_000 + i64::from(self.nanosec)
    }

    pub fn from_nanoseconds(nanoseconds: i64) -> Self {
        Self {
            sec: nanoseconds.div_euclid(1_000_000_000) as i32,
            nanosec: nanoseconds.rem_euclid(1_000_000_000) as u32,
        }
    }

    /// The stamp of `seconds`, rounded to the nanosecond (stamps come from ROS headers, so
    /// they round-trip exactly at the precision a header carries).
    pub fn from_seconds(seconds: f64) -> Self {
        let sec = seconds.floor();
        let mut nanosec = ((seconds - sec) * 1e9).round() as u32;
        let mut sec = sec as i32;
        if nanosec >= 1_000_000_000 {
            sec += 1;
            nanosec -= 1_000_000_000;
        }
        Self { sec, nanosec }
    }
}

/// `std_msgs/Header`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    pub stamp: Time,
    #[serde(deserialize_with = "frame_id")]
    pub frame_id: String,
}

fn frame_id<'de, D: Deserializer<'de>>(deserializer: D) -> Result<String, D::Error> {
    name_string(deserializer, "header.frame_id")
}

fn child_frame_id<'de, D: Deserializer<'de>>(deserializer: D) -> Result<String, D::Error> {
    name_string(deserializer, "child_frame_id")
}

/// `geometry_msgs/Point`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Point {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// `geometry_msgs/Vector3`.
pub type Vector3 = Point;

/// `geometry_msgs/Quaternion`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

impl Default for Quaternion {
    fn default() -> Self {
        Self {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 1.0,
        }
    }
}

impl From<&UnitQuaternion<f64>> for Quaternion {
    fn from(q: &UnitQuaternion<f64>) -> Self {
        Self {
            x: q.i,
            y: q.j,
            z: q.k,
            w: q.w,
        }
    }
}

/// `geometry_msgs/Pose`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub position: Point,
    pub orientation: Quaternion,
}

impl From<&Isometry3<f64>> for Pose {
    fn from(pose: &Isometry3<f64>) -> Self {
        let t = pose.translation.vector;
        Self {
            position: Point {
                x: t.x,
                y: t.y,
                z: t.z,
            },
            orientation: Quaternion::from(&pose.rotation),
        }
    }
}

/// `float64[36]`: a 6×6 row-major covariance over `[x y z rot_x rot_y rot_z]`. A fixed-size
/// array is CDR's elements without a length, which serde writes for a tuple (its derive stops
/// at 32 elements, hence this type).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Covariance(pub [f64; 36]);

impl Default for Covariance {
    fn default() -> Self {
        Self([0.0; 36])
    }
}

impl Serialize for Covariance {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        let mut tuple = serializer.serialize_tuple(36)?;
        for value in &self.0 {
            tuple.serialize_element(value)?;
        }
        tuple.end()
    }
}

impl<'de> Deserialize<'de> for Covariance {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct Elements;
        impl<'de> Visitor<'de> for Elements {
            type Value = Covariance;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("36 float64")
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Covariance, A::Error> {
                let mut values = [0.0; 36];
                for (i, value) in values.iter_mut().enumerate() {
                    *value = seq
                        .next_element()?
                        .ok_or_else(|| A::Error::invalid_length(i, &self))?;
                }
                Ok(Covariance(values))
            }
        }
        deserializer.deserialize_tuple(36, Elements)
    }
}

/// `geometry_msgs/PoseWithCovariance`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovariance {
    pub pose: Pose,
    pub covariance: Covariance,
}

/// `geometry_msgs/Twist`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Twist {
    pub linear: Vector3,
    pub angular: Vector3,
}

/// `geometry_msgs/TwistWithCovariance`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TwistWithCovariance {
    pub twist: Twist,
    pub covariance: Covariance,
}

/// `nav_msgs/Odometry`: `pose` in `header.frame_id`, `twist` in `child_frame_id` (the body).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Odometry {
    pub header: Header,
    #[serde(deserialize_with = "child_frame_id")]
    pub child_frame_id: String,
    pub pose: PoseWithCovariance,
    pub twist: TwistWithCovariance,
}

/// `geometry_msgs/PoseWithCovarianceStamped`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovarianceStamped {
    pub header: Header,
    pub pose: PoseWithCovariance,
}

/// `geometry_msgs/PoseStamped`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseStamped {
    pub header: Header,
    pub pose: Pose,
}

/// `nav_msgs/Path`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Path {
    pub header: Header,
    pub poses: Vec<PoseStamped>,
}

/// `sensor_msgs/Imu`. Covariances are 3×3 row-major (`float64[9]`: a fixed array, which serde
/// writes as a tuple, as CDR wants); `orientation` is not used (the window integrates the gyro).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Imu {
    pub header: Header,
    pub orientation: Quaternion,
    pub orientation_covariance: [f64; 9],
    pub angular_velocity: Vector3,
    pub angular_velocity_covariance: [f64; 9],
    pub linear_acceleration: Vector3,
    pub linear_acceleration_covariance: [f64; 9],
}

/// `geometry_msgs/Transform`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Transform {
    pub translation: Vector3,
    pub rotation: Quaternion,
}

impl From<&Isometry3<f64>> for Transform {
    fn from(pose: &Isometry3<f64>) -> Self {
        let Pose {
            position,
            orientation,
        } = Pose::from(pose);
        Self {
            translation: position,
            rotation: orientation,
        }
    }
}

/// `geometry_msgs/TransformStamped`: `child_frame_id`'s pose in `header.frame_id`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TransformStamped {
    pub header: Header,
    pub child_frame_id: String,
    pub transform: Transform,
}

/// `tf2_msgs/TFMessage`, what `/tf` carries.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TfMessage {
    pub transforms: Vec<TransformStamped>,
}

/// `factord_msgs/LoopClosure`: `relative_pose` is the pose at `to_stamp` in the body frame of
/// the pose at `from_stamp`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LoopClosure {
    pub header: Header,
    pub from_stamp: Time,
    pub to_stamp: Time,
    pub relative_pose: Pose,
    pub covariance: Covariance,
    pub may_be_wrong: bool,
}

/// `factord_msgs/RobotLoopClosure`: an inter-robot closure, the robots named by their namespace
/// or id; as a [`LoopClosure`] once they are known.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RobotLoopClosure {
    pub header: Header,
    pub from_robot: String,
    pub from_stamp: Time,
    pub to_robot: String,
    pub to_stamp: Time,
    pub relative_pose: Pose,
    pub covariance: Covariance,
    pub may_be_wrong: bool,
}

impl RobotLoopClosure {
    /// The closure between the two robots' keyframes, without their names.
    pub fn closure(&self) -> LoopClosure {
        LoopClosure {
            header: self.header.clone(),
            from_stamp: self.from_stamp,
            to_stamp: self.to_stamp,
            relative_pose: self.relative_pose,
            covariance: self.covariance,
            may_be_wrong: self.may_be_wrong,
        }
    }
}

/// `factord_msgs/LandmarkSighting`: a landmark's position in the body frame at `header.stamp`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LandmarkSighting {
    pub header: Header,
    pub landmark_id: u64,
    pub position: Point,
    /// 3×3 row-major over `[x y z]`, m².
    pub covariance: [f64; 9],
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stamps_round_trip_at_nanosecond_precision() {
        let t = Time {
            sec: 1_700_000_000,
            nanosec: 123_456_789,
        };
        assert_eq!(Time::from_seconds(t.seconds()).sec, t.sec);
        let back = Time::from_seconds(t.seconds()).nanosec as i64;
        // f64 holds ~16 digits: 10 for the seconds leave ~100 ns for the fraction.
        assert!((back - t.nanosec as i64).abs() < 500, "{back}");
        assert_eq!(
            Time::from_seconds(2.9999999999),
            Time { sec: 3, nanosec: 0 }
        );
        assert_eq!(Time::from_nanoseconds(t.nanoseconds()), t);
        assert_eq!(
            Time::from_nanoseconds(-1),
            Time {
                sec: -1,
                nanosec: 999_999_999
            }
        );
    }
}
