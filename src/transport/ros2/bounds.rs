//! The values a ROS message may bring in, checked after decoding and before anything of it is
//! used: a message outside them is refused whole (`ros2_bad_message`, naming the field as the
//! `.msg` definition does, `pose.pose.position.x`), never clamped or partly applied.
//!
//! - Stamps: `nanosec` below 10⁹, never negative, and on each topic strictly after the previous
//!   message used there ([`Stamps`]). An equal stamp is a duplicate (a republished or replayed
//!   message): dropped and reported, since applying it would make a second keyframe at the same
//!   time (a TUM export with a repeated time) or count a prior's information twice.
//! - Positions within ±[`MAX_POSITION`] m: beyond any map (ECEF coordinates are below 7·10⁶ m),
//!   yet far from where squared residuals overflow.
//! - Orientations unit within [`UNIT_TOLERANCE`] (then normalised); a quaternion of norm near 0
//!   (all zeros, as unset fields are) is refused rather than normalised into an arbitrary
//!   rotation. `sensor_msgs/Imu`'s orientation is not used (the window integrates the gyro) and
//!   may be all zeros, as ROS allows for an IMU without one: it is not checked.
//! - Velocities and IMU readings finite and within physical bounds ([`MAX_SPEED`],
//!   [`MAX_ANGULAR_VELOCITY`], [`MAX_ACCELERATION`]): far above what any robot or MEMS IMU
//!   reports (±16 g and ±35 rad/s are typical full scales), far below what breaks integration.
//!
//! Strings (`frame_id`) are bounded as they are decoded (`messages::name_string`); covariances
//! are checked where they are inverted (`keyframes::information`, `window_feed::sigmas`).

use super::messages::{
    Imu, LandmarkSighting, LoopClosure, Odometry, Point, Pose, PoseWithCovarianceStamped, Time,
};

/// The largest |coordinate| of a position, in metres.
pub const MAX_POSITION: f64 = 1e9;
/// The largest |component| of a linear velocity (odometry's twist), m/s.
pub const MAX_SPEED: f64 = 1e4;
/// The largest |component| of an angular velocity (twist, gyro), rad/s.
pub const MAX_ANGULAR_VELOCITY: f64 = 1e3;
/// The largest |component| of a linear acceleration (IMU), m/s² (about 1000 g).
pub const MAX_ACCELERATION: f64 = 1e4;
/// How far from 1 a quaternion's norm may be (ROS publishes unit quaternions; tf2 itself refuses
/// those off by more than 1e-2).
pub use crate::geometry::so3::UNIT_NORM_TOLERANCE as UNIT_TOLERANCE;

/// A value of a ROS message outside what is taken.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum BadValue {
    #[error("{field} is {value:?}: not a finite number")]
    NonFinite { field: &'static str, value: f64 },
    #[error("{field} is {value:?}: beyond ±{bound:e} {unit}")]
    OutOfRange {
        field: &'static str,
        value: f64,
        bound: f64,
        unit: &'static str,
    },
    #[error("{field} has norm {norm:?}: not a unit quaternion (within {UNIT_TOLERANCE:e})")]
    NotUnit { field: &'static str, norm: f64 },
    #[error("{field}.nanosec is {nanosec}: at most 999999999")]
    Nanoseconds { field: &'static str, nanosec: u32 },
    #[error("landmark_id is {id}: at most {MAX_LANDMARK_ID} (2^56 - 1)")]
    LandmarkId { id: u64 },
    #[error("{field} is {t:?} s: ROS stamps are not negative")]
    NegativeStamp { field: &'static str, t: f64 },
    #[error("{field} {t:?} s is before the previous {topic} message's ({previous:?} s): out of order, dropped")]
    StampBefore {
        field: &'static str,
        topic: &'static str,
        t: f64,
        previous: f64,
    },
    #[error("{field} {t:?} s is the previous {topic} message's: a duplicate, dropped")]
    DuplicateStamp {
        field: &'static str,
        topic: &'static str,
        t: f64,
    },
}

const STAMP: &str = "header.stamp";

/// An odometry message's values; its stamp in seconds (whose order is [`Stamps`]' to check).
pub fn odometry(message: &Odometry) -> Result<f64, BadValue> {
    let t = stamp(message.header.stamp)?;
    pose(&message.pose.pose)?;
    let twist = &message.twist.twist;
    let linear = [
        "twist.twist.linear.x",
        "twist.twist.linear.y",
        "twist.twist.linear.z",
    ];
    vector(&twist.linear, linear, MAX_SPEED, "m/s")?;
    let angular = [
        "twist.twist.angular.x",
        "twist.twist.angular.y",
        "twist.twist.angular.z",
    ];
    vector(&twist.angular, angular, MAX_ANGULAR_VELOCITY, "rad/s")?;
    Ok(t)
}

/// An absolute pose's values; its stamp in seconds.
pub fn prior(message: &PoseWithCovarianceStamped) -> Result<f64, BadValue> {
    let t = stamp(message.header.stamp)?;
    pose(&message.pose.pose)?;
    Ok(t)
}

/// An IMU sample's values (not its orientation: see the module's doc); its stamp in seconds.
pub fn imu(message: &Imu) -> Result<f64, BadValue> {
    let t = stamp(message.header.stamp)?;
    let gyro = [
        "angular_velocity.x",
        "angular_velocity.y",
        "angular_velocity.z",
    ];
    vector(
        &message.angular_velocity,
        gyro,
        MAX_ANGULAR_VELOCITY,
        "rad/s",
    )?;
    let accel = [
        "linear_acceleration.x",
        "linear_acceleration.y",
        "linear_acceleration.z",
    ];
    vector(
        &message.linear_acceleration,
        accel,
        MAX_ACCELERATION,
        "m/s²",
    )?;
    Ok(t)
}

/// The field names of a pose, as its message's definition spells them.
struct PoseFields {
    position: [&'static str; 3],
    orientation: [&'static str; 4],
    quaternion: &'static str,
}

const POSE_POSE: PoseFields = PoseFields {
    position: [
        "pose.pose.position.x",
        "pose.pose.position.y",
        "pose.pose.position.z",
    ],
    orientation: [
        "pose.pose.orientation.x",
        "pose.pose.orientation.y",
        "pose.pose.orientation.z",
        "pose.pose.orientation.w",
    ],
    quaternion: "pose.pose.orientation",
};

const RELATIVE_POSE: PoseFields = PoseFields {
    position: [
        "relative_pose.position.x",
        "relative_pose.position.y",
        "relative_pose.position.z",
    ],
    orientation: [
        "relative_pose.orientation.x",
        "relative_pose.orientation.y",
        "relative_pose.orientation.z",
        "relative_pose.orientation.w",
    ],
    quaternion: "relative_pose.orientation",
};

/// `pose.pose` of an odometry message or an absolute pose: position and orientation.
pub fn pose(pose: &Pose) -> Result<(), BadValue> {
    pose_named(pose, &POSE_POSE)
}

fn pose_named(pose: &Pose, names: &PoseFields) -> Result<(), BadValue> {
    vector(&pose.position, names.position, MAX_POSITION, "m")?;
    let o = pose.orientation;
    for (field, value) in names.orientation.into_iter().zip([o.x, o.y, o.z, o.w]) {
        finite(field, value)?;
    }
    let q = nalgebra::Quaternion::new(o.w, o.x, o.y, o.z);
    crate::geometry::so3::unit_within_tolerance(q).map_err(|norm| BadValue::NotUnit {
        field: names.quaternion,
        norm,
    })?;
    Ok(())
}

/// A loop closure's values: its three stamps and its relative pose; its header stamp.
pub fn loop_closure(message: &LoopClosure) -> Result<f64, BadValue> {
    let t = stamp(message.header.stamp)?;
    stamp_named(message.from_stamp, "from_stamp")?;
    stamp_named(message.to_stamp, "to_stamp")?;
    pose_named(&message.relative_pose, &RELATIVE_POSE)?;
    Ok(t)
}

/// Landmark ids become keys `('l' << 56) | id`: ids must leave the tag's byte alone.
pub const MAX_LANDMARK_ID: u64 = (1 << 56) - 1;

/// A landmark sighting's values: stamp, id and position; its stamp.
pub fn landmark(message: &LandmarkSighting) -> Result<f64, BadValue> {
    let t = stamp(message.header.stamp)?;
    if message.landmark_id > MAX_LANDMARK_ID {
        return Err(BadValue::LandmarkId {
            id: message.landmark_id,
        });
    }
    let position = ["position.x", "position.y", "position.z"];
    vector(&message.position, position, MAX_POSITION, "m")?;
    Ok(t)
}

/// A header stamp in seconds: well-formed and not negative.
pub fn stamp(time: Time) -> Result<f64, BadValue> {
    stamp_named(time, STAMP)
}

fn stamp_named(time: Time, field: &'static str) -> Result<f64, BadValue> {
    if time.nanosec >= 1_000_000_000 {
        return Err(BadValue::Nanoseconds {
            field,
            nanosec: time.nanosec,
        });
    }
    let t = time.seconds();
    if time.sec < 0 {
        return Err(BadValue::NegativeStamp { field, t });
    }
    Ok(t)
}

fn vector(
    v: &Point,
    fields: [&'static str; 3],
    bound: f64,
    unit: &'static str,
) -> Result<(), BadValue> {
    for (field, value) in fields.into_iter().zip([v.x, v.y, v.z]) {
        finite(field, value)?;
        if value.abs() > bound {
            return Err(BadValue::OutOfRange {
                field,
                value,
                bound,
                unit,
            });
        }
    }
    Ok(())
}

fn finite(field: &'static str, value: f64) -> Result<(), BadValue> {
    match value.is_finite() {
        true => Ok(()),
        false => Err(BadValue::NonFinite { field, value }),
    }
}

/// The newest stamp used on each input topic of a binding: a message must come strictly after
/// it. Checked before a message is used and recorded once it has been, so a refused message
/// (a bad covariance) does not move it.
#[derive(Debug, Default)]
pub struct Stamps {
    newest: [Option<f64>; 3],
}

/// A binding's input topics, as [`Stamps`] counts them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stream {
    Odometry = 0,
    Prior = 1,
    Imu = 2,
}

impl Stream {
    fn name(self) -> &'static str {
        match self {
            Stream::Odometry => "odometry",
            Stream::Prior => "absolute pose",
            Stream::Imu => "IMU",
        }
    }
}

impl Stamps {
    /// After a restart: odometry before `t` (the newest keyframe's stamp) is refused as it was
    /// before the restart, so keyframes stay in time order.
    pub fn resume_after(&mut self, t: f64) {
        self.newest[Stream::Odometry as usize] = Some(t);
    }

    /// Whether `t` may be used on `stream`.
    pub fn check(&self, stream: Stream, t: f64) -> Result<(), BadValue> {
        let (field, topic) = (STAMP, stream.name());
        match self.newest[stream as usize] {
            Some(previous) if t == previous => Err(BadValue::DuplicateStamp { field, topic, t }),
            Some(previous) if t < previous => Err(BadValue::StampBefore {
                field,
                topic,
                t,
                previous,
            }),
            _ => Ok(()),
        }
    }

    /// `t` was used on `stream`.
    pub fn record(&mut self, stream: Stream, t: f64) {
        self.newest[stream as usize] = Some(t);
    }

    /// The newest stamp used on `stream`.
    pub fn newest(&self, stream: Stream) -> Option<f64> {
        self.newest[stream as usize]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn odometry_at(sec: i32) -> Odometry {
        let mut o = Odometry::default();
        o.header.stamp = Time { sec, nanosec: 0 };
        o
    }

    #[test]
    fn stamps_must_be_well_formed_not_negative_and_increasing() {
        assert!(matches!(
            odometry(&odometry_at(-5)),
            Err(BadValue::NegativeStamp { t, .. }) if t == -5.0
        ));
        let bad = Time {
            sec: 1,
            nanosec: 1_000_000_000,
        };
        assert!(matches!(stamp(bad), Err(BadValue::Nanoseconds { .. })));
        let mut stamps = Stamps::default();
        assert_eq!(stamps.check(Stream::Odometry, 2.0), Ok(()));
        stamps.record(Stream::Odometry, 2.0);
        assert!(matches!(
            stamps.check(Stream::Odometry, 2.0),
            Err(BadValue::DuplicateStamp { .. })
        ));
        assert!(matches!(
            stamps.check(Stream::Odometry, 1.0),
            Err(BadValue::StampBefore { .. })
        ));
        // Each topic has its own order.
        assert_eq!(stamps.check(Stream::Imu, 1.0), Ok(()));
    }

    #[test]
    fn closures_and_sightings_name_their_own_fields() {
        let mut c = LoopClosure::default();
        c.header.stamp = Time { sec: 3, nanosec: 0 };
        assert_eq!(loop_closure(&c), Ok(3.0));
        c.to_stamp.nanosec = 1_000_000_000;
        assert!(matches!(
            loop_closure(&c),
            Err(BadValue::Nanoseconds {
                field: "to_stamp",
                ..
            })
        ));
        c.to_stamp.nanosec = 0;
        c.from_stamp.sec = -1;
        assert!(matches!(
            loop_closure(&c),
            Err(BadValue::NegativeStamp {
                field: "from_stamp",
                ..
            })
        ));
        c.from_stamp.sec = 0;
        c.relative_pose.position.z = f64::NAN;
        assert!(matches!(
            loop_closure(&c),
            Err(BadValue::NonFinite {
                field: "relative_pose.position.z",
                ..
            })
        ));
        c.relative_pose.position.z = 0.0;
        c.relative_pose.orientation.w = 0.5;
        assert!(matches!(
            loop_closure(&c),
            Err(BadValue::NotUnit {
                field: "relative_pose.orientation",
                ..
            })
        ));
        let mut l = LandmarkSighting {
            landmark_id: MAX_LANDMARK_ID,
            ..Default::default()
        };
        assert_eq!(landmark(&l), Ok(0.0));
        l.landmark_id += 1;
        assert_eq!(landmark(&l), Err(BadValue::LandmarkId { id: 1 << 56 }));
        l.landmark_id = 7;
        l.position.x = -2e9;
        assert!(matches!(
            landmark(&l),
            Err(BadValue::OutOfRange {
                field: "position.x",
                ..
            })
        ));
    }

    #[test]
    fn values_are_finite_and_bounded_and_orientations_unit() {
        let mut o = odometry_at(1);
        o.pose.pose.position.x = 1e300;
        let error = odometry(&o).unwrap_err();
        assert!(
            error
                .to_string()
                .starts_with("pose.pose.position.x is 1e300"),
            "{error}"
        );
        o.pose.pose.position.x = 1e9;
        assert_eq!(odometry(&o), Ok(1.0));
        o.pose.pose.orientation.w = 0.0;
        assert!(matches!(odometry(&o), Err(BadValue::NotUnit { norm, .. }) if norm == 0.0));
        o.pose.pose.orientation.w = 1.0;
        o.twist.twist.linear.y = f64::NAN;
        assert!(matches!(
            odometry(&o),
            Err(BadValue::NonFinite {
                field: "twist.twist.linear.y",
                ..
            })
        ));
        let mut sample = Imu::default();
        sample.linear_acceleration.z = -2e4;
        assert!(matches!(
            imu(&sample),
            Err(BadValue::OutOfRange {
                field: "linear_acceleration.z",
                ..
            })
        ));
    }
}
