//! A robot's fusion stream built from EuRoC by `fusion::experiment`, as wire messages.

use factord::fusion::experiment::{self, FusionInputs, Generation};
use factord::io::euroc;
use serde_json::{json, Value};

/// The experiment's inputs over the first `seconds`, or `None` (skipped) without the data.
pub fn inputs(seconds: f64, window: usize) -> Option<FusionInputs> {
    let imu = super::data_file("imu/euroc_V1_01_easy/imu0.csv")?;
    let data = euroc::load(imu.parent().unwrap(), "groundtruth_20hz_tum.txt").unwrap();
    let generation = Generation {
        seconds,
        window,
        ..Generation::default()
    };
    Some(experiment::generate(&data, &generation).unwrap())
}

pub fn start_message(inputs: &FusionInputs) -> Value {
    let i = &inputs.initial;
    json!({
        "type": "start", "t": i.t, "position": i.position, "rotation_xyzw": i.rotation_xyzw,
        "velocity": i.velocity, "sigmas": i.sigmas, "window": inputs.window,
        "gravity": inputs.gravity, "imu_noise": inputs.imu_noise,
    })
}

/// One message batch per keyframe: the IMU samples up to it, the keyframe, its relative pose
/// and its prior, as a robot would send them.
pub fn keyframe_batches(inputs: &FusionInputs) -> Vec<Vec<Value>> {
    let mut samples = inputs.imu.iter().peekable();
    inputs
        .keyframes
        .iter()
        .map(|k| {
            let mut messages = Vec::new();
            while let Some(s) = samples.next_if(|s| s[0] <= k.t) {
                messages
                    .push(json!({"type": "imu", "t": s[0], "accel": &s[1..4], "gyro": &s[4..7]}));
            }
            messages.push(json!({"type": "keyframe", "t": k.t}));
            for r in inputs.relative_poses.iter().filter(|r| r.to == k.key) {
                messages.push(json!({"type": "relative_pose", "from": r.from, "to": r.to,
                    "position": r.position, "rotation_xyzw": r.rotation_xyzw,
                    "sigma_position": r.sigma_position, "sigma_rotation": r.sigma_rotation}));
            }
            for p in inputs.pose_priors.iter().filter(|p| p.key == k.key) {
                messages.push(
                    json!({"type": "pose_prior", "key": p.key, "position": p.position,
                    "rotation_xyzw": p.rotation_xyzw, "sigma_position": p.sigma_position,
                    "sigma_rotation": p.sigma_rotation}),
                );
            }
            messages
        })
        .collect()
}

pub fn position_error(inputs: &FusionInputs, state: &Value) -> f64 {
    let key = state["key"].as_u64().unwrap();
    let truth = &inputs
        .keyframes
        .iter()
        .find(|k| k.key == key)
        .unwrap()
        .truth;
    (0..3)
        .map(|i| (state["position"][i].as_f64().unwrap() - truth.position[i]).powi(2))
        .sum::<f64>()
        .sqrt()
}
