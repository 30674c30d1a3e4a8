//! `factord fusion-eval`: the sliding-window fusion experiment on EuRoC — make (or read) the
//! inputs, run the window here or stream them to a server over zenoh, report APE and timings.

use std::path::PathBuf;

use factord::fusion::experiment::{self, Generation};
use factord::io;
use factord::transport::fusion_client::{self, AfterRun};

use super::CliError;

#[derive(clap::Args)]
pub struct FusionEvalArgs {
    /// EuRoC directory with imu0.csv and the ground truth
    #[arg(long, default_value = "../shared/data/imu/euroc_V1_01_easy")]
    data: PathBuf,
    /// Ground-truth file in that directory (TUM format)
    #[arg(long, default_value = "groundtruth_20hz_tum.txt")]
    truth: String,
    /// Run on these inputs (as written by --inputs-out) instead of making new ones
    #[arg(long)]
    inputs: Option<PathBuf>,
    /// Keyframes in the window
    #[arg(long, default_value_t = 10)]
    window: usize,
    /// Seconds of the sequence to use
    #[arg(long, default_value_t = 140.0)]
    seconds: f64,
    #[arg(long, default_value_t = 2024)]
    seed: u64,
    /// Leave out the IMU (keyframes linked by relative poses and priors only)
    #[arg(long)]
    no_imu: bool,
    /// Leave out the map-matching priors
    #[arg(long)]
    no_priors: bool,
    /// Leave out the lidar relative poses
    #[arg(long)]
    no_relative: bool,
    /// Write the inputs (for GTSAM: benches/fusion/gtsam_fixed_lag.py)
    #[arg(long)]
    inputs_out: Option<PathBuf>,
    /// Write the estimated trajectory (newest state after each keyframe) in TUM format
    #[arg(long)]
    tum_out: Option<PathBuf>,
    /// Write the lag-smoothed trajectory (each keyframe as it left the window) in TUM format
    /// (in process only)
    #[arg(long)]
    tum_smoothed_out: Option<PathBuf>,
    /// Print the result as JSON
    #[arg(long)]
    json: bool,
    /// Stream the inputs to a running `factord serve` over zenoh (this endpoint, e.g.
    /// tcp/127.0.0.1:7447) as a robot would, instead of running the window in this process
    #[arg(long)]
    zenoh: Option<String>,
    /// Session name to create on that server
    #[arg(long, default_value = "fusion-eval")]
    session: String,
    /// Keep that session afterwards (to read its `estimate?format=tum` or marginals)
    #[arg(long, requires = "zenoh")]
    keep_session: bool,
}

pub fn run(args: FusionEvalArgs) -> Result<(), CliError> {
    let inputs = match &args.inputs {
        Some(path) => {
            let text = std::fs::read_to_string(path).map_err(CliError::file(path))?;
            serde_json::from_str(&text).map_err(|source| CliError::FileContents {
                path: path.clone(),
                source,
            })?
        }
        None => {
            let data = io::euroc::load(&args.data, &args.truth)?;
            let generation = Generation {
                seconds: args.seconds,
                prior_every: if args.no_priors { 0 } else { 10 },
                use_relative: !args.no_relative,
                use_imu: !args.no_imu,
                window: args.window,
                seed: args.seed,
                ..Generation::default()
            };
            experiment::generate(&data, &generation).map_err(CliError::Reported)?
        }
    };
    if let Some(path) = &args.inputs_out {
        let text = serde_json::to_string(&inputs)?;
        std::fs::write(path, text).map_err(CliError::file(path))?;
    }
    // In process, also the lag-smoothed trajectory (each keyframe as it left the window).
    let (estimates, smoothed) = match &args.zenoh {
        Some(endpoint) => (
            tokio::runtime::Builder::new_multi_thread()
                .worker_threads(2)
                .enable_all()
                .build()
                .map_err(CliError::Runtime)?
                .block_on(fusion_client::stream_over_zenoh(
                    endpoint,
                    &args.session,
                    &inputs,
                    if args.keep_session {
                        AfterRun::Keep
                    } else {
                        AfterRun::Delete
                    },
                ))
                .map_err(CliError::Reported)?,
            None,
        ),
        None => {
            let (real_time, smoothed) = experiment::run_smoothed(&inputs)?;
            (real_time, Some(smoothed))
        }
    };
    let smoothed_ape = smoothed.as_ref().map(|s| experiment::ape(&inputs, s));
    let (full, trans) = experiment::ape(&inputs, &estimates);
    let update = experiment::Percentiles::of(
        &estimates
            .iter()
            .map(|e| e.update_seconds * 1e3)
            .collect::<Vec<_>>(),
    );
    let latency: Option<Vec<f64>> = estimates
        .iter()
        .map(|e| e.latency_seconds.map(|s| s * 1e3))
        .collect();
    if let (Some(path), Some(smoothed)) = (&args.tum_smoothed_out, &smoothed) {
        std::fs::write(path, experiment::tum(&inputs, smoothed)).map_err(CliError::file(path))?;
    }
    if let Some(path) = &args.tum_out {
        std::fs::write(path, experiment::tum(&inputs, &estimates)).map_err(CliError::file(path))?;
    }
    let result = serde_json::json!({
        "generation": inputs.generation,
        "window": inputs.window,
        "use_imu": inputs.use_imu,
        "keyframes": estimates.len(),
        "relative_poses": inputs.relative_poses.len(),
        "pose_priors": inputs.pose_priors.len(),
        "ape_full": full,
        "ape_trans": trans,
        // Each keyframe's estimate as it left the window (in process only).
        "ape_smoothed_full": smoothed_ape.as_ref().map(|a| &a.0),
        "ape_smoothed_trans": smoothed_ape.as_ref().map(|a| &a.1),
        "update_ms": update,
        // Over zenoh: from publishing a keyframe's messages to its state's arrival.
        "latency_ms": latency.map(|l| experiment::Percentiles::of(&l)),
        "through": if args.zenoh.is_some() { "zenoh" } else { "in-process" },
        "iterations_mean": estimates.iter().map(|e| e.iterations as f64).sum::<f64>()
            / estimates.len().max(1) as f64,
    });
    if args.json {
        println!("{result}");
    } else {
        println!("{}", serde_json::to_string_pretty(&result)?);
    }
    Ok(())
}
