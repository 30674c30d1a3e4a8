//! The window engine: a robot streams IMU samples, keyframes, lidar relative poses and
//! map-matching / GNSS priors; the session keeps a [`SlidingWindow`], optimises it at every
//! keyframe and publishes the newest state (`out/state`) and the whole window (`out/window`).
//!
//! Messages are applied in order. A refused message (out-of-order IMU, a prior on a
//! marginalised keyframe, …) stops the batch there: the messages before it stay applied, the
//! error names its index, and the window is as it was before that message.

use std::sync::MutexGuard;
use std::time::Instant;

use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use super::engine::{self, Engine, SmoothedKeyframe};
use super::Session;
use crate::api::fusion::{
    FusionAck, FusionBatch, FusionMessage, PreintegratedKeyframeMessage, StartMessage, StateReport,
};
use crate::api::wire::{SessionEvent, VariableValue};
use crate::api::ServiceError;
use crate::fusion::window::{diagonal_information, FusionError, SlidingWindow, WindowOptions};
use crate::geometry::preintegration::{ImuNoise, Matrix15, Preintegrated};
use crate::geometry::{so3, NavState};
use crate::problem::Key;

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

/// `q` (x, y, z, w) as a unit quaternion, refused unless finite with a norm within
/// [`so3::UNIT_NORM_TOLERANCE`] of 1, as batches (B5) and ROS inputs (S31) are.
fn unit_quaternion(field: &'static str, q: &[f64; 4]) -> Result<UnitQuaternion<f64>, FusionError> {
    finite(q)?;
    so3::unit_within_tolerance(Quaternion::new(q[3], q[0], q[1], q[2])).map_err(|norm| {
        FusionError::Invalid {
            field,
            reason: format!(
                "a rotation quaternion's norm must be within {} of 1, got {norm:e}",
                so3::UNIT_NORM_TOLERANCE
            ),
        }
    })
}

/// Applies one message; `Ok(Some(key))` when it created a keyframe.
fn apply(
    window: &mut Option<SlidingWindow>,
    message: FusionMessage,
) -> Result<Option<Key>, FusionError> {
    if let FusionMessage::Start(start) = message {
        if window.is_some() {
            return Err(FusionError::Invalid {
                field: "type",
                reason: "the session has already started".into(),
            });
        }
        *window = Some(start_window(*start)?);
        return Ok(Some(0));
    }
    let w = window.as_mut().ok_or_else(|| FusionError::Invalid {
        field: "type",
        reason: engine::start_first(),
    })?;
    match message {
        FusionMessage::Start(_) => unreachable!("handled above"),
        FusionMessage::Imu { t, accel, gyro } => {
            w.add_imu(t, Vector3::from(accel), Vector3::from(gyro))?;
            Ok(None)
        }
        FusionMessage::Keyframe { t } => {
            let key = w.add_keyframe(t)?;
            Ok(Some(key))
        }
        FusionMessage::PreintegratedKeyframe(keyframe) => {
            let t = keyframe.t;
            let measurement = preintegrated(w.options.imu_noise, *keyframe)?;
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
            let q = unit_quaternion("rotation_xyzw", &rotation_xyzw)?;
            let info = diagonal_information(&[(sigma_position, 3), (sigma_rotation, 3)])?;
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
            let q = unit_quaternion("rotation_xyzw", &rotation_xyzw)?;
            let info = diagonal_information(&[(sigma_position, 3), (sigma_rotation, 3)])?;
            w.add_pose_prior(key, Vector3::from(position), q, &info)?;
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

/// A new window from a `start` message: its first state, that state's prior and the options.
fn start_window(start: StartMessage) -> Result<SlidingWindow, FusionError> {
    let StartMessage {
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
    } = start;
    finite(&[t])?;
    finite(&position)?;
    let rotation = unit_quaternion("rotation_xyzw", &rotation_xyzw)?;
    let first = NavState {
        position: Vector3::from(position),
        rotation,
        velocity: Vector3::from(velocity),
        accel_bias: Vector3::from(accel_bias),
        gyro_bias: Vector3::from(gyro_bias),
    };
    let info = sigmas.information()?;
    let options = WindowOptions {
        size,
        gravity,
        imu_noise,
        ..WindowOptions::default()
    };
    SlidingWindow::new(options, first, t, &info)
}

/// The IMU preintegration a `preintegrated_keyframe` message carries (the robot integrated
/// it), checked finite and of the right sizes.
fn preintegrated(
    imu_noise: ImuNoise,
    keyframe: PreintegratedKeyframeMessage,
) -> Result<Preintegrated, FusionError> {
    let PreintegratedKeyframeMessage {
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
    } = keyframe;
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
        imu_noise,
        Vector3::from(accel_bias),
        Vector3::from(gyro_bias),
    );
    measurement.delta_t = delta_t;
    measurement.delta_rotation = unit_quaternion("delta_rotation_xyzw", &delta_rotation_xyzw)?
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
    Ok(measurement)
}

impl Session {
    /// The window of a window session, locked; fusion messages are refused by graph sessions.
    pub(super) fn locked_window(
        &self,
    ) -> Result<MutexGuard<'_, Option<SlidingWindow>>, ServiceError> {
        match &self.engine {
            Engine::Window(w) => Ok(w.window.lock().unwrap_or_else(|p| p.into_inner())),
            Engine::Graph(_) => Err(engine::fusion_refused(&self.name, self.kind.name)),
        }
    }

    /// Applies `batch`'s messages in order to `guard` (the locked window, see the module
    /// documentation); `applied` counts those the window took, also when a later one is rejected
    /// (they stay applied). Keyframes are optimised as they arrive, after the batch's later
    /// messages for the same keyframe have been added: the window is optimised once per
    /// keyframe, when the next keyframe or the batch's end comes.
    pub(super) fn apply_fusion_counted(
        &self,
        guard: &mut Option<SlidingWindow>,
        batch: FusionBatch,
        applied: &mut usize,
    ) -> Result<FusionAck, ServiceError> {
        let result = self.apply_fusion_messages(guard, batch, applied);
        if *applied > 0 {
            if let Engine::Window(engine) = &self.engine {
                let mut progress = engine.progress.lock().unwrap_or_else(|p| p.into_inner());
                progress.record_batch(guard.as_ref());
            }
        }
        result
    }

    /// [`Self::apply_fusion_counted`] without the batch counter.
    fn apply_fusion_messages(
        &self,
        guard: &mut Option<SlidingWindow>,
        batch: FusionBatch,
        applied: &mut usize,
    ) -> Result<FusionAck, ServiceError> {
        let mut keyframes = Vec::new();
        *applied = 0;
        let mut pending = false;
        let mut started = Instant::now();
        for (index, message) in batch.messages.into_iter().enumerate() {
            let is_keyframe = matches!(
                message,
                FusionMessage::Keyframe { .. } | FusionMessage::PreintegratedKeyframe(_)
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
            smoothed: w
                .departed()
                .iter()
                .map(|(k, t, s)| StateReport::new(*k, *t, s))
                .collect(),
        });
        if let Engine::Window(engine) = &self.engine {
            engine
                .progress
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .record_solve(w, &summary, started.elapsed().as_secs_f64());
            let mut smoothed = engine.smoothed.lock().unwrap_or_else(|p| p.into_inner());
            smoothed.extend(
                w.departed()
                    .iter()
                    .map(|(k, t, s)| keyframe_pose(*k, *t, s)),
            );
        }
        Ok(())
    }

    /// The window session's trajectory as `se3` variables stamped with their time: the
    /// keyframes that left the window as they left (lag-smoothed), then the window's own at its
    /// current optimum. Empty before `start`.
    pub(super) fn window_trajectory(&self) -> Result<Vec<VariableValue>, ServiceError> {
        let window = self.locked_window()?;
        let Engine::Window(engine) = &self.engine else {
            unreachable!("locked_window refuses graph sessions")
        };
        let mut out: Vec<VariableValue> = engine
            .smoothed
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .iter()
            .map(SmoothedKeyframe::as_variable)
            .collect();
        if let Some(w) = window.as_ref() {
            out.extend(
                w.window()
                    .iter()
                    .map(|(k, t, s)| keyframe_pose(*k, *t, s).as_variable()),
            );
        }
        Ok(out)
    }
}

fn keyframe_pose(key: Key, t: f64, state: &NavState) -> SmoothedKeyframe {
    let q = state.rotation.quaternion();
    SmoothedKeyframe {
        key,
        t,
        position: state.position.into(),
        rotation_xyzw: [q.i, q.j, q.k, q.w],
    }
}

impl SmoothedKeyframe {
    /// As an `se3` variable stamped with its time (what trajectory exports read).
    fn as_variable(&self) -> VariableValue {
        let ([x, y, z], [qx, qy, qz, qw]) = (self.position, self.rotation_xyzw);
        VariableValue {
            key: self.key,
            kind: "se3".into(),
            value: smallvec::smallvec![x, y, z, qx, qy, qz, qw],
            changed: 0,
            stamp: Some(self.t),
        }
    }
}
