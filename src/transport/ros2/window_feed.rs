//! From ROS messages to a `sliding_window` session's fusion messages:
//! - the first odometry message starts the window at its pose, with its twist (body frame)
//!   turned into the world velocity;
//! - odometry makes keyframes by the same distance and angle thresholds as in a pose graph
//!   (`keyframes`), each sent with the IMU samples before it and a `relative_pose` from the
//!   previous keyframe;
//! - an absolute pose becomes a `pose_prior` on the keyframe nearest in time.
//!
//! Order. The window takes IMU samples and keyframes in time order, but they come on two
//! topics that are each in order (the caller refuses a stamp not after its topic's previous
//! one, `bounds::Stamps`) and not with each other. So a keyframe waits until an IMU
//! sample at or after its stamp has arrived (all the samples it pre-integrates are then here),
//! and samples go ahead of any keyframe only up to the newest odometry stamp (a keyframe still
//! to come is later than that), in batches of [`SEND_AHEAD_SAMPLES`].
//!
//! Noise. The wire's relative poses and priors take one sigma for position and one for
//! rotation: the square root of the largest variance of each block of the ROS covariance (the
//! conservative choice for a covariance that is not isotropic).

use std::collections::{BTreeMap, VecDeque};

use nalgebra::{Isometry3, Vector3};

use super::keyframes::{has_moved, isometry, nearest_key, stamp_ns, MessageError};
use super::messages::{Covariance, Imu, Odometry, PoseWithCovarianceStamped};
use crate::api::fusion::InitialSigmas;
use crate::api::fusion::{FusionMessage, StartMessage};
use crate::api::ros2::Ros2Binding;
use crate::geometry::preintegration::ImuNoise;
use crate::variables::Key;

/// Relative-pose sigmas (m, rad) for odometry that publishes no covariance.
const DEFAULT_ODOMETRY_SIGMAS: (f64, f64) = (0.05, 0.01);

/// The start state's sigmas: the window's frame is odometry's at the first message, so pose is
/// known well; velocity and biases are what the IMU will tell.
const START_SIGMAS: InitialSigmas = InitialSigmas {
    position: 0.01,
    rotation: 0.01,
    velocity: 0.1,
    accel_bias: 0.1,
    gyro_bias: 0.01,
};

/// Samples that may go ahead of the next keyframe are sent once this many have gathered.
const SEND_AHEAD_SAMPLES: usize = 100;

/// Samples held for keyframes to come: beyond this (odometry stopped while the IMU goes on,
/// about 100 s at 200 Hz) new samples are refused rather than held without bound.
const MAX_HELD_SAMPLES: usize = 20_000;

/// Keyframe stamps kept for priors (far more than any window; older keyframes have left it).
const MAX_STAMPS: usize = 4096;

struct Sample {
    t: f64,
    accel: [f64; 3],
    gyro: [f64; 3],
}

struct Keyframe {
    t: f64,
    odometry_pose: Isometry3<f64>,
    sigmas: (f64, f64),
}

/// What a message makes: fusion batches to send in order (each optimises the window once when
/// it holds a keyframe), and the keyframes they create with their odometry poses.
#[derive(Default)]
pub struct Feed {
    pub batches: Vec<Vec<FusionMessage>>,
    pub keyframes: Vec<(Key, Isometry3<f64>)>,
}

pub struct WindowFeed {
    distance: f64,
    angle: f64,
    window: usize,
    imu_noise: ImuNoise,
    started: bool,
    /// The window's start time (`None` after a restart: the window's own check then applies).
    start_t: Option<f64>,
    next_key: Key,
    /// The newest keyframe sent (`None` after a restart, until odometry says where it is).
    last: Option<(Key, Isometry3<f64>)>,
    /// The pose the thresholds are measured from: the newest keyframe, pending or sent.
    reference: Option<Isometry3<f64>>,
    pending: VecDeque<Keyframe>,
    samples: VecDeque<Sample>,
    samples_since_keyframe: usize,
    newest_imu: Option<f64>,
    newest_odometry: Option<f64>,
    by_stamp: BTreeMap<i64, Key>,
}

impl WindowFeed {
    pub fn new(binding: &Ros2Binding) -> Self {
        Self {
            distance: binding.keyframe_distance,
            angle: binding.keyframe_angle,
            window: binding.window,
            imu_noise: binding.imu_noise,
            started: false,
            start_t: None,
            next_key: 0,
            last: None,
            reference: None,
            pending: VecDeque::new(),
            samples: VecDeque::new(),
            samples_since_keyframe: 0,
            newest_imu: None,
            newest_odometry: None,
            by_stamp: BTreeMap::new(),
        }
    }

    /// Continues a window that already holds keyframes up to `max_key` (after a restart): no
    /// new start; the first keyframe after it has the IMU but no relative pose to connect it.
    pub fn resume_after(&mut self, max_key: Key) {
        self.started = true;
        self.next_key = max_key + 1;
    }

    /// A sample whose values and stamp order the caller has checked (`bounds`).
    pub fn on_imu(&mut self, imu: &Imu) -> Result<Feed, MessageError> {
        let t = imu.header.stamp.seconds();
        let (a, w) = (imu.linear_acceleration, imu.angular_velocity);
        let (accel, gyro) = ([a.x, a.y, a.z], [w.x, w.y, w.z]);
        self.newest_imu = Some(t);
        // The IMU often lags odometry: samples from before the window's start are of no use.
        if self.start_t.is_some_and(|start| t < start) {
            return Ok(Feed::default());
        }
        if self.samples.len() >= MAX_HELD_SAMPLES {
            return Err(MessageError::TooManyHeld {
                held: self.samples.len(),
            });
        }
        self.samples.push_back(Sample { t, accel, gyro });
        Ok(self.flush())
    }

    /// A message whose values and stamp order the caller has checked (`bounds`).
    pub fn on_odometry(&mut self, odometry: &Odometry) -> Result<Feed, MessageError> {
        let pose = isometry(&odometry.pose.pose)?;
        let t = odometry.header.stamp.seconds();
        let sigmas =
            sigmas(&odometry.pose.covariance, "odometry")?.unwrap_or(DEFAULT_ODOMETRY_SIGMAS);
        self.newest_odometry = Some(t);
        let mut feed = Feed::default();
        if !self.started {
            self.started = true;
            self.start_t = Some(t);
            feed.batches.push(vec![self.start(odometry, &pose, t)]);
            feed.keyframes.push((0, pose));
            self.last = Some((0, pose));
            self.reference = Some(pose);
            self.next_key = 1;
            self.by_stamp.insert(stamp_ns(t), 0);
            // The window integrates from its start: earlier samples are of no use.
            self.samples.retain(|s| s.t >= t);
            return Ok(feed);
        }
        match self.reference {
            Some(reference) if !has_moved(&reference, &pose, self.distance, self.angle) => {}
            _ => {
                self.reference = Some(pose);
                self.pending.push_back(Keyframe {
                    t,
                    odometry_pose: pose,
                    sigmas,
                });
            }
        }
        Ok(self.flush())
    }

    /// A `pose_prior` on the keyframe nearest `prior`'s stamp.
    pub fn on_prior(&self, prior: &PoseWithCovarianceStamped) -> Result<Feed, MessageError> {
        let pose = isometry(&prior.pose.pose)?;
        let (sigma_position, sigma_rotation) = sigmas(&prior.pose.covariance, "prior")?
            .ok_or(MessageError::Covariance { what: "prior" })?;
        let key = nearest_key(&self.by_stamp, stamp_ns(prior.header.stamp.seconds()))
            .ok_or(MessageError::NoKeyframeYet)?;
        let (position, rotation_xyzw) = wire_parts(&pose);
        Ok(Feed {
            batches: vec![vec![FusionMessage::PosePrior {
                key,
                position,
                rotation_xyzw,
                sigma_position,
                sigma_rotation,
            }]],
            keyframes: Vec::new(),
        })
    }

    fn start(&self, odometry: &Odometry, pose: &Isometry3<f64>, t: f64) -> FusionMessage {
        let v = odometry.twist.twist.linear;
        let velocity = pose.rotation * Vector3::new(v.x, v.y, v.z);
        let (position, rotation_xyzw) = wire_parts(pose);
        FusionMessage::Start(Box::new(StartMessage {
            t,
            position,
            rotation_xyzw,
            velocity: velocity.into(),
            accel_bias: [0.0; 3],
            gyro_bias: [0.0; 3],
            sigmas: START_SIGMAS,
            window: self.window,
            gravity: 9.81,
            imu_noise: self.imu_noise,
        }))
    }

    /// The keyframes the IMU now covers, each with its samples; then samples that may go ahead.
    fn flush(&mut self) -> Feed {
        let mut feed = Feed::default();
        if !self.started {
            return feed;
        }
        while let Some(keyframe) = self.pending.front() {
            if self.newest_imu.is_none_or(|imu| imu < keyframe.t) {
                break;
            }
            let keyframe = self.pending.pop_front().expect("a front");
            let mut batch = self.samples_through(keyframe.t);
            self.samples_since_keyframe += batch.len();
            if self.samples_since_keyframe == 0 {
                // An IMU gap: nothing to pre-integrate. Not a keyframe; the next one spans it.
                continue;
            }
            let key = self.next_key;
            batch.push(FusionMessage::Keyframe { t: keyframe.t });
            if let Some((from, from_pose)) = self.last {
                let (position, rotation_xyzw) =
                    wire_parts(&(from_pose.inverse() * keyframe.odometry_pose));
                batch.push(FusionMessage::RelativePose {
                    from,
                    to: key,
                    position,
                    rotation_xyzw,
                    sigma_position: keyframe.sigmas.0,
                    sigma_rotation: keyframe.sigmas.1,
                });
            }
            feed.batches.push(batch);
            feed.keyframes.push((key, keyframe.odometry_pose));
            self.last = Some((key, keyframe.odometry_pose));
            self.next_key += 1;
            self.samples_since_keyframe = 0;
            self.by_stamp.insert(stamp_ns(keyframe.t), key);
            while self.by_stamp.len() > MAX_STAMPS {
                self.by_stamp.pop_first();
            }
        }
        if let (true, Some(odometry)) = (self.pending.is_empty(), self.newest_odometry) {
            let ready = self.samples.iter().take_while(|s| s.t <= odometry).count();
            if ready >= SEND_AHEAD_SAMPLES {
                let batch = self.samples_through(odometry);
                self.samples_since_keyframe += batch.len();
                feed.batches.push(batch);
            }
        }
        feed
    }

    /// The held samples at or before `t`, as messages, taken out of the buffer.
    fn samples_through(&mut self, t: f64) -> Vec<FusionMessage> {
        let count = self.samples.iter().take_while(|s| s.t <= t).count();
        self.samples
            .drain(..count)
            .map(|s| FusionMessage::Imu {
                t: s.t,
                accel: s.accel,
                gyro: s.gyro,
            })
            .collect()
    }
}

fn wire_parts(pose: &Isometry3<f64>) -> ([f64; 3], [f64; 4]) {
    let q = pose.rotation.quaternion();
    (pose.translation.vector.into(), [q.i, q.j, q.k, q.w])
}

/// `(σ position, σ rotation)` from a ROS covariance: the square roots of each block's largest
/// variance; `None` when it is all zeros (unknown).
fn sigmas(covariance: &Covariance, what: &'static str) -> Result<Option<(f64, f64)>, MessageError> {
    let c = &covariance.0;
    if c.iter().all(|&v| v == 0.0) {
        return Ok(None);
    }
    let variance = |range: std::ops::Range<usize>| range.map(|i| c[i * 7]).fold(0.0, f64::max);
    let (position, rotation) = (variance(0..3).sqrt(), variance(3..6).sqrt());
    if !(position.is_finite() && rotation.is_finite() && position > 0.0 && rotation > 0.0) {
        return Err(MessageError::Covariance { what });
    }
    Ok(Some((position, rotation)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transport::ros2::messages::{Header, Time};

    fn feed() -> WindowFeed {
        let binding: Ros2Binding = serde_json::from_str(
            r#"{"odometry_topic": "/odom", "imu_topic": "/imu", "keyframe_distance": 1.0}"#,
        )
        .unwrap();
        WindowFeed::new(&binding)
    }

    fn header(t: f64) -> Header {
        Header {
            stamp: Time::from_seconds(t),
            frame_id: "odom".into(),
        }
    }

    fn odometry(t: f64, x: f64) -> Odometry {
        let mut o = Odometry {
            header: header(t),
            ..Default::default()
        };
        o.pose.pose.position.x = x;
        o.twist.twist.linear.x = 1.0;
        o
    }

    fn imu(t: f64) -> Imu {
        let mut m = Imu {
            header: header(t),
            ..Default::default()
        };
        m.linear_acceleration.z = 9.81;
        m
    }

    fn kinds(feed: &Feed) -> Vec<Vec<&'static str>> {
        let kind = |m: &FusionMessage| match m {
            FusionMessage::Start(_) => "start",
            FusionMessage::Imu { .. } => "imu",
            FusionMessage::Keyframe { .. } => "keyframe",
            FusionMessage::RelativePose { .. } => "relative_pose",
            FusionMessage::PosePrior { .. } => "pose_prior",
            _ => "other",
        };
        feed.batches
            .iter()
            .map(|b| {
                let mut kinds: Vec<_> = b.iter().map(kind).collect();
                kinds.dedup();
                kinds
            })
            .collect()
    }

    #[test]
    fn keyframes_wait_for_the_imu_and_carry_its_samples() {
        let mut f = feed();
        // A sample before the start is dropped, whichever topic comes first.
        assert!(f.on_imu(&imu(9.99)).unwrap().batches.is_empty());
        let start = f.on_odometry(&odometry(10.0, 0.0)).unwrap();
        assert_eq!(kinds(&start), [["start"]]);
        let FusionMessage::Start(s) = &start.batches[0][0] else {
            unreachable!()
        };
        assert_eq!((s.t, s.velocity), (10.0, [1.0, 0.0, 0.0]));
        assert!(f.on_imu(&imu(9.995)).unwrap().batches.is_empty());
        assert!(f.on_imu(&imu(10.5)).unwrap().batches.is_empty());
        // Odometry ahead of the IMU: the keyframe at 11 waits for a sample at or after it.
        assert!(f
            .on_odometry(&odometry(11.0, 1.2))
            .unwrap()
            .batches
            .is_empty());
        assert!(f.on_imu(&imu(10.9)).unwrap().batches.is_empty());
        let keyframe = f.on_imu(&imu(11.0)).unwrap();
        assert_eq!(kinds(&keyframe), [["imu", "keyframe", "relative_pose"]]);
        assert_eq!(keyframe.batches[0].len(), 3 + 2);
        assert_eq!(keyframe.keyframes[0].0, 1);
        let FusionMessage::RelativePose {
            from, to, position, ..
        } = &keyframe.batches[0][4]
        else {
            unreachable!()
        };
        assert_eq!((*from, *to, position[0]), (0, 1, 1.2));
    }

    #[test]
    fn samples_go_ahead_up_to_the_newest_odometry_and_priors_find_the_nearest_keyframe() {
        let mut f = feed();
        f.on_odometry(&odometry(0.0, 0.0)).unwrap();
        // The robot stands still: no keyframe; samples up to the newest odometry go in hundreds.
        let mut sent = 0;
        for i in 1..=250 {
            let t = f64::from(i) * 0.005;
            if i % 10 == 0 {
                assert!(f.on_odometry(&odometry(t, 0.0)).unwrap().batches.is_empty());
            }
            let feed = f.on_imu(&imu(t)).unwrap();
            assert!(feed.keyframes.is_empty());
            sent += feed.batches.iter().map(Vec::len).sum::<usize>();
        }
        assert_eq!(
            sent, 200,
            "two batches of samples that no keyframe can precede"
        );
        f.on_odometry(&odometry(2.0, 1.5)).unwrap();
        assert_eq!(f.on_imu(&imu(2.0)).unwrap().keyframes[0].0, 1);
        let mut prior = PoseWithCovarianceStamped {
            header: header(1.9),
            ..Default::default()
        };
        prior.pose.covariance.0[0] = 0.04;
        prior.pose.covariance.0[35] = 0.0001;
        let batches = f.on_prior(&prior).unwrap().batches;
        let FusionMessage::PosePrior {
            key,
            sigma_position,
            sigma_rotation,
            ..
        } = batches[0][0]
        else {
            unreachable!()
        };
        assert_eq!(key, 1);
        assert!((sigma_position - 0.2).abs() < 1e-12 && (sigma_rotation - 0.01).abs() < 1e-12);
    }

    #[test]
    fn a_resumed_feed_does_not_start_again() {
        let mut f = feed();
        f.resume_after(41);
        assert!(f
            .on_odometry(&odometry(5.0, 0.0))
            .unwrap()
            .batches
            .is_empty());
        let keyframe = f.on_imu(&imu(5.0)).unwrap();
        assert_eq!(kinds(&keyframe), [["imu", "keyframe"]]);
        assert_eq!(keyframe.keyframes[0].0, 42);
    }
}
