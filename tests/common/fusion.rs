//! A robot's fusion stream built from EuRoC by `eval/experiment.rs`, as wire messages.

use super::eval::experiment::{self, experiment_messages, FusionInputs, Generation};
use factord::io::euroc;
use serde_json::Value;

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
    serde_json::to_value(experiment_messages(inputs).0).unwrap()
}

/// One message batch per keyframe, as a robot would send them.
pub fn keyframe_batches(inputs: &FusionInputs) -> Vec<Vec<Value>> {
    experiment_messages(inputs)
        .1
        .into_iter()
        .map(|batch| {
            batch
                .into_iter()
                .map(|m| serde_json::to_value(m).unwrap())
                .collect()
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
