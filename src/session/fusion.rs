//! The `sliding_window` session kind: a robot streams IMU samples, keyframes, lidar relative
//! poses and map-matching / GNSS priors; the session keeps a [`SlidingWindow`], optimises it at
//! every keyframe and publishes the newest state (`out/state`) and the whole window
//! (`out/window`).
//!
//! Messages are applied in order. A refused message (out-of-order IMU, a prior on a
//! marginalised keyframe, …) stops the batch there: the messages before it stay applied, the
//! error names its index, and the window is as it was before that message.

use std::time::Instant;

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use super::wire::SessionEvent;
use super::wire_number;
use super::Session;
use crate::fusion::experiment::InitialSigmas;
use crate::fusion::preintegration::{ImuNoise, Matrix15, Preintegrated};
use crate::fusion::window::{
    diagonal_information, quaternion_xyzw, FusionError, SlidingWindow, WindowOptions,
};
use crate::geometry::NavState;
use crate::problem::Key;
use crate::service::ServiceError;

/// A batch of fusion messages (`POST /v1/sessions/{s}/fusion`, zenoh `…/in/fusion`).
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct FusionBatch {
    #[serde(deserialize_with = "super::wire_list::items")]
    pub messages: Vec<FusionMessage>,
}

fn default_window() -> usize {
    10
}
fn default_gravity() -> f64 {
    9.81
}
fn default_noise() -> ImuNoise {
    ImuNoise::EUROC
}

#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum FusionMessage {
    /// The first keyframe (key 0) and the window's parameters; once per session.
    Start {
        t: f64,
        position: [f64; 3],
        rotation_xyzw: [f64; 4],
        #[serde(default)]
        velocity: [f64; 3],
        #[serde(default)]
        accel_bias: [f64; 3],
        #[serde(default)]
        gyro_bias: [f64; 3],
        sigmas: InitialSigmas,
        #[serde(default = "default_window", deserialize_with = "wire_number::usize")]
        window: usize,
        #[serde(default = "default_gravity")]
        gravity: f64,
        #[serde(default = "default_noise")]
        imu_noise: ImuNoise,
    },
    /// One IMU sample: accelerometer m/s², gyroscope rad/s, body frame.
    Imu {
        t: f64,
        accel: [f64; 3],
        gyro: [f64; 3],
    },
    /// A keyframe at `t` from the samples since the previous one; the window is then optimised.
    Keyframe { t: f64 },
    /// A keyframe at `t` from a measurement pre-integrated on the robot since the previous
    /// keyframe (GTSAM's manifold pre-integration: matrices row-major, the covariance 15×15 in
    /// the order rotation, position, velocity, accelerometer bias, gyroscope bias).
    PreintegratedKeyframe {
        t: f64,
        delta_t: f64,
        delta_rotation_xyzw: [f64; 4],
        delta_velocity: [f64; 3],
        delta_position: [f64; 3],
        /// The bias the samples were corrected with.
        accel_bias: [f64; 3],
        gyro_bias: [f64; 3],
        d_rotation_d_gyro_bias: [f64; 9],
        d_velocity_d_accel_bias: [f64; 9],
        d_velocity_d_gyro_bias: [f64; 9],
        d_position_d_accel_bias: [f64; 9],
        d_position_d_gyro_bias: [f64; 9],
        covariance: Vec<f64>,
    },
    /// Lidar odometry: the pose of `to` in the frame of `from`.
    RelativePose {
        #[serde(deserialize_with = "wire_number::u64")]
        from: Key,
        #[serde(deserialize_with = "wire_number::u64")]
        to: Key,
        position: [f64; 3],
        rotation_xyzw: [f64; 4],
        sigma_position: f64,
        sigma_rotation: f64,
    },
    /// Map matching: the world pose of `key`.
    PosePrior {
        #[serde(deserialize_with = "wire_number::u64")]
        key: Key,
        position: [f64; 3],
        rotation_xyzw: [f64; 4],
        sigma_position: f64,
        sigma_rotation: f64,
    },
    /// GNSS: the world position of `key`.
    PositionPrior {
        #[serde(deserialize_with = "wire_number::u64")]
        key: Key,
        position: [f64; 3],
        sigma: f64,
    },
}

/// The experiment's inputs as a robot sends them: the `start` message, then one batch per
/// keyframe (its IMU samples, the keyframe, its relative poses and priors).
pub fn experiment_messages(
    inputs: &crate::fusion::experiment::FusionInputs,
) -> (FusionMessage, Vec<Vec<FusionMessage>>) {
    let i = &inputs.initial;
    let start = FusionMessage::Start {
        t: i.t,
        position: i.position,
        rotation_xyzw: i.rotation_xyzw,
        velocity: i.velocity,
        accel_bias: i.accel_bias,
        gyro_bias: i.gyro_bias,
        sigmas: i.sigmas.clone(),
        window: inputs.window,
        gravity: inputs.gravity,
        imu_noise: inputs.imu_noise,
    };
    let mut samples = inputs.imu.iter().peekable();
    let batches = inputs
        .keyframes
        .iter()
        .map(|k| {
            let mut messages = Vec::new();
            while let Some(s) = samples.next_if(|s| s[0] <= k.t) {
                messages.push(FusionMessage::Imu {
                    t: s[0],
                    accel: [s[1], s[2], s[3]],
                    gyro: [s[4], s[5], s[6]],
                });
            }
            messages.push(FusionMessage::Keyframe { t: k.t });
            for r in inputs.relative_poses.iter().filter(|r| r.to == k.key) {
                messages.push(FusionMessage::RelativePose {
                    from: r.from,
                    to: r.to,
                    position: r.position,
                    rotation_xyzw: r.rotation_xyzw,
                    sigma_position: r.sigma_position,
                    sigma_rotation: r.sigma_rotation,
                });
            }
            for p in inputs.pose_priors.iter().filter(|p| p.key == k.key) {
                messages.push(FusionMessage::PosePrior {
                    key: p.key,
                    position: p.position,
                    rotation_xyzw: p.rotation_xyzw,
                    sigma_position: p.sigma_position,
                    sigma_rotation: p.sigma_rotation,
                });
            }
            messages
        })
        .collect();
    (start, batches)
}

/// One keyframe's state on the wire.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct StateReport {
    pub key: Key,
    pub t: f64,
    pub position: [f64; 3],
    pub rotation_xyzw: [f64; 4],
    pub velocity: [f64; 3],
    pub accel_bias: [f64; 3],
    pub gyro_bias: [f64; 3],
}

impl StateReport {
    fn new(key: Key, t: f64, s: &NavState) -> Self {
        let q = s.rotation.quaternion();
        let a = |v: &Vector3<f64>| [v.x, v.y, v.z];
        Self {
            key,
            t,
            position: a(&s.position),
            rotation_xyzw: [q.i, q.j, q.k, q.w],
            velocity: a(&s.velocity),
            accel_bias: a(&s.accel_bias),
            gyro_bias: a(&s.gyro_bias),
        }
    }
}

/// What a fusion batch did.
#[derive(Clone, Debug, Serialize)]
pub struct FusionAck {
    pub session: String,
    pub applied: usize,
    /// Keys of the keyframes the batch created, in order.
    pub keyframes: Vec<Key>,
    /// The newest state after the batch (after its last keyframe's optimisation).
    pub latest: Option<StateReport>,
}

fn finite(values: &[f64]) -> Result<(), FusionError> {
    if values.iter().all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(FusionError::Invalid {
            field: "values",
            reason: "a number is not finite".into(),
        })
    }
}

/// Applies one message; `Ok(Some(key))` when it created a keyframe.
fn apply(
    window: &mut Option<SlidingWindow>,
    message: FusionMessage,
) -> Result<Option<Key>, FusionError> {
    if let FusionMessage::Start {
        t,
        position,
        rotation_xyzw,
        velocity,
        accel_bias,
        gyro_bias,
        sigmas,
        window: size,
        gravity,
        imu_noise,
    } = message
    {
        if window.is_some() {
            return Err(FusionError::Invalid {
                field: "type",
                reason: "the session has already started".into(),
            });
        }
        finite(&[t])?;
        finite(&position)?;
        finite(&rotation_xyzw)?;
        let first = NavState {
            position: Vector3::from(position),
            rotation: quaternion_xyzw(&rotation_xyzw),
            velocity: Vector3::from(velocity),
            accel_bias: Vector3::from(accel_bias),
            gyro_bias: Vector3::from(gyro_bias),
        };
        let s = &sigmas;
        let info = diagonal_information(&[
            (s.position, 3),
            (s.rotation, 3),
            (s.velocity, 3),
            (s.accel_bias, 3),
            (s.gyro_bias, 3),
        ])?;
        let options = WindowOptions {
            size,
            gravity,
            imu_noise,
            ..WindowOptions::default()
        };
        *window = Some(SlidingWindow::new(options, first, t, &info)?);
        return Ok(Some(0));
    }
    let w = window.as_mut().ok_or(FusionError::Invalid {
        field: "type",
        reason: "the first message of a sliding_window session must be `start`".into(),
    })?;
    match message {
        FusionMessage::Start { .. } => unreachable!("handled above"),
        FusionMessage::Imu { t, accel, gyro } => {
            w.add_imu(t, Vector3::from(accel), Vector3::from(gyro))?;
            Ok(None)
        }
        FusionMessage::Keyframe { t } => {
            let key = w.add_keyframe(t)?;
            Ok(Some(key))
        }
        FusionMessage::PreintegratedKeyframe {
            t,
            delta_t,
            delta_rotation_xyzw,
            delta_velocity,
            delta_position,
            accel_bias,
            gyro_bias,
            d_rotation_d_gyro_bias,
            d_velocity_d_accel_bias,
            d_velocity_d_gyro_bias,
            d_position_d_accel_bias,
            d_position_d_gyro_bias,
            covariance,
        } => {
            if covariance.len() != 225 {
                return Err(FusionError::Invalid {
                    field: "covariance",
                    reason: format!("expected 225 numbers (15×15), got {}", covariance.len()),
                });
            }
            for values in [
                &[t, delta_t][..],
                &delta_rotation_xyzw,
                &delta_velocity,
                &delta_position,
                &accel_bias,
                &gyro_bias,
                &d_rotation_d_gyro_bias,
                &d_velocity_d_accel_bias,
                &d_velocity_d_gyro_bias,
                &d_position_d_accel_bias,
                &d_position_d_gyro_bias,
                &covariance,
            ] {
                finite(values)?;
            }
            let matrix = |m: &[f64; 9]| nalgebra::Matrix3::from_row_slice(m);
            let mut measurement = Preintegrated::new(
                w.options.imu_noise,
                Vector3::from(accel_bias),
                Vector3::from(gyro_bias),
            );
            measurement.delta_t = delta_t;
            measurement.delta_rotation = quaternion_xyzw(&delta_rotation_xyzw)
                .to_rotation_matrix()
                .into_inner();
            measurement.delta_velocity = Vector3::from(delta_velocity);
            measurement.delta_position = Vector3::from(delta_position);
            measurement.d_rotation_d_gyro_bias = matrix(&d_rotation_d_gyro_bias);
            measurement.d_velocity_d_accel_bias = matrix(&d_velocity_d_accel_bias);
            measurement.d_velocity_d_gyro_bias = matrix(&d_velocity_d_gyro_bias);
            measurement.d_position_d_accel_bias = matrix(&d_position_d_accel_bias);
            measurement.d_position_d_gyro_bias = matrix(&d_position_d_gyro_bias);
            measurement.covariance = Matrix15::from_row_slice(&covariance);
            measurement.samples = 1;
            let key = w.add_keyframe_preintegrated(t, measurement)?;
            Ok(Some(key))
        }
        FusionMessage::RelativePose {
            from,
            to,
            position,
            rotation_xyzw,
            sigma_position,
            sigma_rotation,
        } => {
            finite(&position)?;
            finite(&rotation_xyzw)?;
            let info = diagonal_information(&[(sigma_position, 3), (sigma_rotation, 3)])?;
            let q = quaternion_xyzw(&rotation_xyzw);
            w.add_relative_pose(from, to, Vector3::from(position), q, &info)?;
            Ok(None)
        }
        FusionMessage::PosePrior {
            key,
            position,
            rotation_xyzw,
            sigma_position,
            sigma_rotation,
        } => {
            finite(&position)?;
            finite(&rotation_xyzw)?;
            let info = diagonal_information(&[(sigma_position, 3), (sigma_rotation, 3)])?;
            w.add_pose_prior(
                key,
                Vector3::from(position),
                quaternion_xyzw(&rotation_xyzw),
                &info,
            )?;
            Ok(None)
        }
        FusionMessage::PositionPrior {
            key,
            position,
            sigma,
        } => {
            finite(&position)?;
            let info = diagonal_information(&[(sigma, 3)])?;
            w.add_position_prior(key, Vector3::from(position), &info)?;
            Ok(None)
        }
    }
}

impl Session {
    /// Applies a fusion batch (see the module documentation). Keyframes are optimised as they
    /// arrive, after the batch's later messages for the same keyframe have been added: the
    /// window is optimised once per keyframe, when the next keyframe or the batch's end comes.
    /// Applies `batch`'s messages in order to `guard` (the locked window); `applied` counts those
    /// the window took, also when a later one is rejected (they stay applied).
    pub(super) fn apply_fusion_counted(
        &self,
        guard: &mut Option<SlidingWindow>,
        batch: FusionBatch,
        applied: &mut usize,
    ) -> Result<FusionAck, ServiceError> {
        if self.kind.name != super::catalogue::SLIDING_WINDOW {
            return Err(ServiceError::bad_request(
                "wrong_kind",
                "session",
                format!(
                    "session `{}` is of kind {}; fusion messages go to sliding_window sessions",
                    self.name, self.kind.name
                ),
            ));
        }
        let mut keyframes = Vec::new();
        *applied = 0;
        let mut pending = false;
        let mut started = Instant::now();
        for (index, message) in batch.messages.into_iter().enumerate() {
            let is_keyframe = matches!(
                message,
                FusionMessage::Keyframe { .. } | FusionMessage::PreintegratedKeyframe { .. }
            );
            if is_keyframe && pending {
                self.optimize_window(guard, started, *applied)?;
                pending = false;
            }
            if is_keyframe {
                started = Instant::now();
            }
            match apply(guard, message) {
                Ok(Some(key)) => {
                    keyframes.push(key);
                    pending = is_keyframe;
                }
                Ok(None) => {}
                Err(e) => {
                    if pending {
                        self.optimize_window(guard, started, *applied)?;
                    }
                    let field = format!("messages[{index}]");
                    let message = format!("{e} (the {index} message(s) before it were applied)");
                    // Malformed values are the request's fault (400); a message that does not
                    // fit the window's current state (order, marginalised keys) is 422.
                    return Err(match e {
                        FusionError::Invalid { .. } => {
                            ServiceError::bad_request("invalid_message", field, message)
                        }
                        _ => ServiceError::invalid("rejected_message", field, message),
                    });
                }
            }
            *applied += 1;
        }
        if pending {
            self.optimize_window(guard, started, *applied)?;
        }
        let latest = guard.as_ref().map(|w| {
            let (key, t, state) = w.latest();
            StateReport::new(key, t, &state)
        });
        Ok(FusionAck {
            session: self.name.clone(),
            applied: *applied,
            keyframes,
            latest,
        })
    }

    /// Optimises after a keyframe. A failure does not undo the messages before it (`applied`,
    /// the keyframe included): they stay in the window and the journal, as they would in a
    /// session whose solve fails after a batch was accepted.
    fn optimize_window(
        &self,
        window: &mut Option<SlidingWindow>,
        started: Instant,
        applied: usize,
    ) -> Result<(), ServiceError> {
        let w = window.as_mut().expect("a keyframe exists only after start");
        let summary = w.optimize().map_err(|e| {
            let message = format!(
                "{e} (the window's solve failed; the {applied} message(s) before this point, \
                 its keyframe included, stay applied and the window keeps its last estimate)"
            );
            ServiceError::invalid("solve_failed", "messages", message)
        })?;
        let (key, t, state) = w.latest();
        self.emit(SessionEvent::State {
            session: self.name.clone(),
            state: StateReport::new(key, t, &state),
            iterations: summary.iterations,
            update_seconds: started.elapsed().as_secs_f64(),
        });
        self.emit(SessionEvent::Window {
            session: self.name.clone(),
            keyframes: w
                .window()
                .iter()
                .map(|(k, t, s)| StateReport::new(*k, *t, s))
                .collect(),
        });
        Ok(())
    }
}
