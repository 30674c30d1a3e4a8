//! The course's fusion experiment, reproducible and shareable: measurements made from a EuRoC
//! sequence (real IMU samples, keyframes at 10 Hz, lidar-like relative poses and map-matching
//! priors from the ground truth with known Gaussian noise and a fixed seed), written as one
//! JSON inputs file that our window and GTSAM's fixed-lag smoother (`benches/fusion/
//! gtsam_fixed_lag.py`) both consume; and the absolute pose error as `evo_ape` reports it.

use std::time::Instant;

use nalgebra::{Matrix4, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use factord::api::fusion::{FusionMessage, InitialSigmas, StartMessage};
use factord::factors::testing::Rng;
use factord::fusion::window::{
    diagonal_information, quaternion_xyzw, FusionError, SlidingWindow, WindowOptions,
};
use factord::geometry::preintegration::ImuNoise;
use factord::geometry::{so3, NavState};
use factord::io::euroc::Euroc;
use factord::problem::Key;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseJson {
    pub position: [f64; 3],
    /// Hamilton quaternion, x y z w.
    pub rotation_xyzw: [f64; 4],
}

impl PoseJson {
    fn new(position: &Vector3<f64>, rotation: &UnitQuaternion<f64>) -> Self {
        let q = rotation.quaternion();
        Self {
            position: [position.x, position.y, position.z],
            rotation_xyzw: [q.i, q.j, q.k, q.w],
        }
    }
    pub fn position(&self) -> Vector3<f64> {
        Vector3::from(self.position)
    }
    pub fn rotation(&self) -> UnitQuaternion<f64> {
        quaternion_xyzw(&self.rotation_xyzw)
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct InitialState {
    pub key: Key,
    pub t: f64,
    pub position: [f64; 3],
    pub rotation_xyzw: [f64; 4],
    pub velocity: [f64; 3],
    pub accel_bias: [f64; 3],
    pub gyro_bias: [f64; 3],
    pub sigmas: InitialSigmas,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct KeyframeInput {
    pub key: Key,
    pub t: f64,
    pub truth: PoseJson,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RelativeInput {
    pub from: Key,
    pub to: Key,
    pub position: [f64; 3],
    pub rotation_xyzw: [f64; 4],
    pub sigma_position: f64,
    pub sigma_rotation: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PriorInput {
    pub key: Key,
    pub position: [f64; 3],
    pub rotation_xyzw: [f64; 4],
    pub sigma_position: f64,
    pub sigma_rotation: f64,
}

/// Everything both estimators see.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FusionInputs {
    /// How the inputs were made (parameters, seed, data), for the record.
    pub generation: serde_json::Value,
    /// Unix seconds to add to every `t` (TUM output uses absolute times).
    pub origin: i64,
    pub gravity: f64,
    pub imu_noise: ImuNoise,
    pub window: usize,
    pub keyframe_hz: f64,
    pub use_imu: bool,
    pub initial: InitialState,
    pub initial_truth: PoseJson,
    /// `[t, ax, ay, az, gx, gy, gz]`.
    pub imu: Vec<[f64; 7]>,
    pub keyframes: Vec<KeyframeInput>,
    pub relative_poses: Vec<RelativeInput>,
    pub pose_priors: Vec<PriorInput>,
}

/// How to make the inputs from a sequence.
#[derive(Clone, Debug, Serialize)]
pub struct Generation {
    pub seconds: f64,
    /// Keyframe every this many ground-truth poses (20 Hz ground truth: 2 → 10 Hz).
    pub truth_stride: usize,
    /// First keyframe at this ground-truth index.
    pub first_truth: usize,
    /// A map-matching prior every this many keyframes (10 → 1 Hz); 0: none.
    pub prior_every: usize,
    pub relative_sigma_position: f64,
    pub relative_sigma_rotation: f64,
    pub prior_sigma_position: f64,
    pub prior_sigma_rotation: f64,
    pub use_relative: bool,
    pub use_imu: bool,
    pub window: usize,
    pub seed: u64,
}

impl Default for Generation {
    fn default() -> Self {
        Self {
            seconds: 140.0,
            truth_stride: 2,
            first_truth: 20,
            prior_every: 10,
            relative_sigma_position: 0.02,
            relative_sigma_rotation: 0.005,
            prior_sigma_position: 0.1,
            prior_sigma_rotation: 0.02,
            use_relative: true,
            use_imu: true,
            window: 10,
            seed: 2024,
        }
    }
}

fn array3(v: &Vector3<f64>) -> [f64; 3] {
    [v.x, v.y, v.z]
}

/// Makes the inputs; fails when the sequence is too short for one keyframe.
pub fn generate(data: &Euroc, g: &Generation) -> Result<FusionInputs, String> {
    let truth = &data.truth;
    if truth.len() < g.first_truth + 2 * g.truth_stride {
        return Err("the ground truth is too short".into());
    }
    let mut rng = Rng::new(g.seed);
    let first = &truth[g.first_truth];
    let next = &truth[g.first_truth + 1];
    let velocity = (next.position - first.position) / (next.t - first.t);
    let mut keyframes = Vec::new();
    let mut relative_poses = Vec::new();
    let mut pose_priors = Vec::new();
    let mut previous = (0, first);
    let mut index = g.first_truth + g.truth_stride;
    let mut key = 1;
    while index < truth.len() && truth[index].t <= first.t + g.seconds {
        let pose = &truth[index];
        keyframes.push(KeyframeInput {
            key,
            t: pose.t,
            truth: PoseJson::new(&pose.position, &pose.rotation),
        });
        if g.use_relative {
            let (from, before) = previous;
            let dp = before.rotation.inverse() * (pose.position - before.position)
                + rng.vector3(g.relative_sigma_position);
            let dq = before.rotation.inverse()
                * pose.rotation
                * so3::exp(&rng.vector3(g.relative_sigma_rotation));
            let rel = PoseJson::new(&dp, &dq);
            relative_poses.push(RelativeInput {
                from,
                to: key,
                position: rel.position,
                rotation_xyzw: rel.rotation_xyzw,
                sigma_position: g.relative_sigma_position,
                sigma_rotation: g.relative_sigma_rotation,
            });
        }
        if g.prior_every > 0 && (key as usize).is_multiple_of(g.prior_every) {
            let p = pose.position + rng.vector3(g.prior_sigma_position);
            let q = pose.rotation * so3::exp(&rng.vector3(g.prior_sigma_rotation));
            let prior = PoseJson::new(&p, &q);
            pose_priors.push(PriorInput {
                key,
                position: prior.position,
                rotation_xyzw: prior.rotation_xyzw,
                sigma_position: g.prior_sigma_position,
                sigma_rotation: g.prior_sigma_rotation,
            });
        }
        previous = (key, pose);
        key += 1;
        index += g.truth_stride;
    }
    let end = keyframes.last().map_or(first.t, |k| k.t);
    let imu = data
        .imu
        .iter()
        .filter(|s| s.t > first.t && s.t <= end)
        .map(|s| {
            [
                s.t, s.accel.x, s.accel.y, s.accel.z, s.gyro.x, s.gyro.y, s.gyro.z,
            ]
        })
        .collect();
    let initial_pose = PoseJson::new(&first.position, &first.rotation);
    let keyframe_hz = 1.0 / (truth[g.first_truth + g.truth_stride].t - first.t);
    Ok(FusionInputs {
        generation: serde_json::to_value(g).expect("plain data"),
        origin: data.origin,
        gravity: 9.81,
        imu_noise: ImuNoise::EUROC,
        window: g.window,
        keyframe_hz,
        use_imu: g.use_imu,
        initial: InitialState {
            key: 0,
            t: first.t,
            position: initial_pose.position,
            rotation_xyzw: initial_pose.rotation_xyzw,
            velocity: array3(&velocity),
            accel_bias: [0.0; 3],
            gyro_bias: [0.0; 3],
            sigmas: InitialSigmas {
                position: 0.01,
                rotation: 0.01,
                velocity: 0.1,
                accel_bias: 0.1,
                gyro_bias: 0.01,
            },
        },
        initial_truth: initial_pose,
        imu,
        keyframes,
        relative_poses,
        pose_priors,
    })
}

/// One estimate per keyframe (the newest state right after that keyframe's update).
#[derive(Clone, Debug, Serialize)]
pub struct Estimate {
    pub key: Key,
    pub t: f64,
    pub pose: PoseJson,
    /// The window's update: adding the keyframe's measurements, optimising, marginalising
    /// (measured in this process, or by the server and reported in its `state` event).
    pub update_seconds: f64,
    pub iterations: usize,
    /// Over zenoh: from publishing the keyframe's messages to its state's arrival.
    pub latency_seconds: Option<f64>,
}

/// Runs our sliding window over `inputs` as a robot would feed it, in time order.
pub fn run(inputs: &FusionInputs) -> Result<Vec<Estimate>, FusionError> {
    run_smoothed(inputs).map(|(real_time, _)| real_time)
}

/// [`run`], and the lag-smoothed trajectory: each keyframe's estimate when it leaves the
/// window (marginalised after the optimisation that saw the window's newest keyframe), and for
/// those still in the window at the end, their final estimate. `update_seconds` is the update
/// it left in; in time order.
pub fn run_smoothed(inputs: &FusionInputs) -> Result<(Vec<Estimate>, Vec<Estimate>), FusionError> {
    let i = &inputs.initial;
    let pose = PoseJson {
        position: i.position,
        rotation_xyzw: i.rotation_xyzw,
    };
    let first = NavState {
        position: pose.position(),
        rotation: pose.rotation(),
        velocity: Vector3::from(i.velocity),
        accel_bias: Vector3::from(i.accel_bias),
        gyro_bias: Vector3::from(i.gyro_bias),
    };
    let information = i.sigmas.information()?;
    let mut options = WindowOptions {
        size: inputs.window,
        gravity: inputs.gravity,
        imu_noise: inputs.imu_noise,
        ..WindowOptions::default()
    };
    if !inputs.use_imu {
        // Velocities and biases are then unobserved: LM's damping holds them.
        options.solver = factord::solver::SolverOptions {
            max_iterations: options.solver.max_iterations,
            ..factord::solver::SolverOptions::bundle_adjustment()
        };
    }
    let mut window = SlidingWindow::new(options, first, i.t, &information)?;
    let mut keys = std::collections::HashMap::from([(i.key, 0)]);
    let mut samples = inputs.imu.iter().peekable();
    let mut estimates = Vec::with_capacity(inputs.keyframes.len());
    let mut smoothed = Vec::with_capacity(inputs.keyframes.len());
    // The window's keys back to the inputs' keys.
    let mut input_key = std::collections::HashMap::from([(0, i.key)]);
    let smoothed_estimate = |key: Key, t: f64, state: &NavState, update: &Estimate| Estimate {
        key,
        t,
        pose: PoseJson::new(&state.position, &state.rotation),
        ..update.clone()
    };
    for keyframe in &inputs.keyframes {
        let start = Instant::now();
        if inputs.use_imu {
            while let Some(s) = samples.next_if(|s| s[0] <= keyframe.t) {
                window.add_imu(
                    s[0],
                    Vector3::new(s[1], s[2], s[3]),
                    Vector3::new(s[4], s[5], s[6]),
                )?;
            }
        }
        let relatives: Vec<&RelativeInput> = inputs
            .relative_poses
            .iter()
            .filter(|r| r.to == keyframe.key)
            .collect();
        let key = if inputs.use_imu {
            window.add_keyframe(keyframe.t)?
        } else {
            // Without an IMU the first relative pose (or the previous state) is the guess.
            let (_, _, latest) = window.latest();
            let mut guess = latest;
            if let Some(r) = relatives.first() {
                let rel = PoseJson {
                    position: r.position,
                    rotation_xyzw: r.rotation_xyzw,
                };
                guess.position = latest.position + latest.rotation * rel.position();
                guess.rotation = latest.rotation * rel.rotation();
            }
            window.add_keyframe_without_imu(keyframe.t, guess)?
        };
        keys.insert(keyframe.key, key);
        input_key.insert(key, keyframe.key);
        for r in relatives {
            let from = *keys
                .get(&r.from)
                .ok_or(FusionError::NotInWindow { key: r.from })?;
            let rel = PoseJson {
                position: r.position,
                rotation_xyzw: r.rotation_xyzw,
            };
            let information =
                diagonal_information(&[(r.sigma_position, 3), (r.sigma_rotation, 3)])?;
            window.add_relative_pose(from, key, rel.position(), rel.rotation(), &information)?;
        }
        for p in inputs.pose_priors.iter().filter(|p| p.key == keyframe.key) {
            let prior = PoseJson {
                position: p.position,
                rotation_xyzw: p.rotation_xyzw,
            };
            let information =
                diagonal_information(&[(p.sigma_position, 3), (p.sigma_rotation, 3)])?;
            window.add_pose_prior(key, prior.position(), prior.rotation(), &information)?;
        }
        let summary = window.optimize()?;
        let (_, t, state) = window.latest();
        let estimate = Estimate {
            key: keyframe.key,
            t,
            pose: PoseJson::new(&state.position, &state.rotation),
            update_seconds: start.elapsed().as_secs_f64(),
            iterations: summary.iterations,
            latency_seconds: None,
        };
        for (key, t, state) in window.departed() {
            smoothed.push(smoothed_estimate(input_key[key], *t, state, &estimate));
        }
        estimates.push(estimate);
    }
    if let Some(last) = estimates.last() {
        for (key, t, state) in window.window() {
            smoothed.push(smoothed_estimate(input_key[&key], t, &state, last));
        }
    }
    Ok((estimates, smoothed))
}

/// Percentiles of durations (or anything), nearest rank.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Percentiles {
    pub p50: f64,
    pub p90: f64,
    pub p99: f64,
    pub max: f64,
    pub count: usize,
}

impl Percentiles {
    pub fn of(values: &[f64]) -> Self {
        let mut sorted = values.to_vec();
        sorted.sort_by(f64::total_cmp);
        let at = |p: f64| {
            sorted
                .get(((sorted.len() as f64 - 1.0) * p).round() as usize)
                .copied()
                .unwrap_or(f64::NAN)
        };
        Self {
            p50: at(0.5),
            p90: at(0.9),
            p99: at(0.99),
            max: at(1.0),
            count: sorted.len(),
        }
    }
}

/// `evo_ape`'s statistics of a list of errors (std is the population standard deviation).
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct ErrorStatistics {
    pub max: f64,
    pub mean: f64,
    pub median: f64,
    pub min: f64,
    pub rmse: f64,
    pub sse: f64,
    pub std: f64,
}

impl ErrorStatistics {
    pub fn of(errors: &[f64]) -> Self {
        let n = errors.len().max(1) as f64;
        let mut sorted = errors.to_vec();
        sorted.sort_by(f64::total_cmp);
        let median = match sorted.len() {
            0 => f64::NAN,
            l if l % 2 == 1 => sorted[l / 2],
            l => 0.5 * (sorted[l / 2 - 1] + sorted[l / 2]),
        };
        let mean = errors.iter().sum::<f64>() / n;
        let sse: f64 = errors.iter().map(|e| e * e).sum();
        Self {
            max: sorted.last().copied().unwrap_or(f64::NAN),
            mean,
            median,
            min: sorted.first().copied().unwrap_or(f64::NAN),
            rmse: (sse / n).sqrt(),
            sse,
            std: (errors.iter().map(|e| (e - mean) * (e - mean)).sum::<f64>() / n).sqrt(),
        }
    }
}

fn matrix(pose: &PoseJson) -> Matrix4<f64> {
    let mut m = Matrix4::identity();
    m.fixed_view_mut::<3, 3>(0, 0)
        .copy_from(pose.rotation().to_rotation_matrix().matrix());
    m.fixed_view_mut::<3, 1>(0, 3).copy_from(&pose.position());
    m
}

/// APE against the keyframes' ground truth, as `evo_ape … -r full` (‖T_truth⁻¹ T_est − I‖_F,
/// unitless) and `-r trans_part` (metres), without alignment (same world frame).
pub fn ape(inputs: &FusionInputs, estimates: &[Estimate]) -> (ErrorStatistics, ErrorStatistics) {
    let truth: std::collections::HashMap<Key, &PoseJson> =
        inputs.keyframes.iter().map(|k| (k.key, &k.truth)).collect();
    let (mut full, mut trans) = (Vec::new(), Vec::new());
    for e in estimates {
        let Some(t) = truth.get(&e.key) else { continue };
        let error = matrix(t).try_inverse().expect("a pose is invertible") * matrix(&e.pose);
        full.push((error - Matrix4::identity()).norm());
        trans.push((e.pose.position() - t.position()).norm());
    }
    (ErrorStatistics::of(&full), ErrorStatistics::of(&trans))
}

/// The estimates as TUM lines (`t x y z qx qy qz qw`, absolute seconds).
pub fn tum(inputs: &FusionInputs, estimates: &[Estimate]) -> String {
    let mut out = String::from(factord::io::tum::TIMESTAMP_HEADER);
    for e in estimates {
        let stamp = inputs.origin as f64 + e.t;
        factord::io::tum::push_line(&mut out, stamp, e.pose.position, e.pose.rotation_xyzw);
    }
    out
}

/// The experiment's inputs as a robot sends them: the `start` message, then one batch per
/// keyframe (its IMU samples, the keyframe, its relative poses and priors).
pub fn experiment_messages(inputs: &FusionInputs) -> (FusionMessage, Vec<Vec<FusionMessage>>) {
    let i = &inputs.initial;
    let start = FusionMessage::Start(Box::new(StartMessage {
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
    }));
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
