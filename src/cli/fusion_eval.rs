//! `factord fusion-eval`: the sliding-window fusion experiment on EuRoC — make (or read) the
//! inputs, run the window here or stream them to a server over zenoh, report APE and timings.

use std::path::PathBuf;

use crate::eval::experiment::{self, Estimate, FusionInputs, Generation};
use crate::eval::fusion_client::{self, AfterRun};
use factord::io;

use super::data_dir;
use super::stdio::{one_stdout, InputArg, OutputArg};
use super::CliError;

/// The default dataset, under the data directory (`FACTORD_DATA`).
const DEFAULT_SEQUENCE: &str = "imu/euroc_V1_01_easy";

#[derive(clap::Args)]
pub struct FusionEvalArgs {
    /// EuRoC directory with imu0.csv and the ground truth [default:
    /// $FACTORD_DATA/imu/euroc_V1_01_easy, FACTORD_DATA defaulting to ../shared/data]
    #[arg(long)]
    data: Option<PathBuf>,
    /// Ground-truth file in that directory (TUM format)
    #[arg(long, default_value = "groundtruth_20hz_tum.txt")]
    truth: String,
    /// Run on these inputs (as written by --inputs-out) instead of making new ones; `-` reads
    /// standard input
    #[arg(long)]
    inputs: Option<InputArg>,
    /// Keyframes in the window
    #[arg(long, default_value_t = 10)]
    window: usize,
    /// Seconds of the sequence to use
    #[arg(long, default_value_t = 140.0)]
    seconds: f64,
    /// Seed of the simulated measurement noise (relative poses and priors)
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
    /// Write the inputs (for GTSAM: benches/fusion/gtsam_fixed_lag.py); `-` for standard output
    #[arg(long)]
    inputs_out: Option<OutputArg>,
    /// Write the estimated trajectory (newest state after each keyframe) in TUM format; `-` for
    /// standard output
    #[arg(long)]
    tum_out: Option<OutputArg>,
    /// Write the lag-smoothed trajectory (each keyframe as it left the window) in TUM format
    /// (in process only); `-` for standard output
    #[arg(long)]
    tum_smoothed_out: Option<OutputArg>,
    /// Print the result as one line of JSON on standard output, instead of the text report
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
    // `--json` takes standard output for the result, as a `-` output would for its data.
    let json_target = OutputArg::Stdout;
    let outputs = [
        ("--json", args.json.then_some(&json_target)),
        ("--inputs-out", args.inputs_out.as_ref()),
        ("--tum-out", args.tum_out.as_ref()),
        ("--tum-smoothed-out", args.tum_smoothed_out.as_ref()),
    ];
    one_stdout(&outputs)?;
    let data_on_stdout = outputs
        .iter()
        .any(|(_, o)| o.is_some_and(OutputArg::is_stdout));
    if args.tum_smoothed_out.is_some() && args.zenoh.is_some() {
        return Err(CliError::Argument {
            argument: "--tum-smoothed-out".into(),
            reason: "the lag-smoothed trajectory is only known in process, not with --zenoh".into(),
        });
    }
    let inputs = load_inputs(&args)?;
    if let Some(target) = &args.inputs_out {
        let text = serde_json::to_string(&inputs)?;
        target.write("--inputs-out", text.as_bytes())?;
    }
    let (estimates, smoothed) = estimate(&args, &inputs)?;
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
    if let (Some(target), Some(smoothed)) = (&args.tum_smoothed_out, &smoothed) {
        let text = experiment::tum(&inputs, smoothed);
        target.write("--tum-smoothed-out", text.as_bytes())?;
    }
    if let Some(target) = &args.tum_out {
        target.write("--tum-out", experiment::tum(&inputs, &estimates).as_bytes())?;
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
    } else if data_on_stdout {
        eprint!("{}", text_report(&result));
    } else {
        print!("{}", text_report(&result));
    }
    Ok(())
}

/// The fusion inputs: `--inputs` as written, or generated from the EuRoC sequence.
fn load_inputs(args: &FusionEvalArgs) -> Result<FusionInputs, CliError> {
    Ok(match &args.inputs {
        Some(input) => {
            let text = input.read_to_string("--inputs")?;
            serde_json::from_str(&text).map_err(|source| CliError::FileContents {
                path: input.name(),
                source,
            })?
        }
        None => {
            let dir = match &args.data {
                Some(dir) => data_dir::existing_dir("--data", dir)?,
                None => data_dir::existing_dir("--data", &data_dir::root().join(DEFAULT_SEQUENCE))?,
            };
            let data = io::euroc::load(&dir, &args.truth)?;
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
    })
}

/// The real-time estimates, streamed over zenoh or run in process (in process, also the
/// lag-smoothed trajectory: each keyframe as it left the window).
fn estimate(
    args: &FusionEvalArgs,
    inputs: &FusionInputs,
) -> Result<(Vec<Estimate>, Option<Vec<Estimate>>), CliError> {
    Ok(match &args.zenoh {
        Some(endpoint) => (
            tokio::runtime::Builder::new_multi_thread()
                .worker_threads(2)
                .enable_all()
                .build()
                .map_err(CliError::Runtime)?
                .block_on(fusion_client::stream_over_zenoh(
                    endpoint,
                    &args.session,
                    inputs,
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
            let (real_time, smoothed) = experiment::run_smoothed(inputs)?;
            (real_time, Some(smoothed))
        }
    })
}

/// The result for a person: one line per figure, APE as evo prints its statistics.
fn text_report(result: &serde_json::Value) -> String {
    let number = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN);
    let statistics = |v: &serde_json::Value| {
        format!(
            "rmse {:.4}  mean {:.4}  median {:.4}  std {:.4}  min {:.4}  max {:.4}",
            number(&v["rmse"]),
            number(&v["mean"]),
            number(&v["median"]),
            number(&v["std"]),
            number(&v["min"]),
            number(&v["max"])
        )
    };
    let percentiles = |v: &serde_json::Value| {
        format!(
            "p50 {:.3}  p90 {:.3}  p99 {:.3}  max {:.3}",
            number(&v["p50"]),
            number(&v["p90"]),
            number(&v["p99"]),
            number(&v["max"])
        )
    };
    let mut out =
        format!(
        "fusion-eval ({}): {} keyframes, window {}, IMU {}, {} relative poses, {} pose priors\n",
        result["through"].as_str().unwrap_or("?"),
        result["keyframes"],
        result["window"],
        if result["use_imu"] == true { "on" } else { "off" },
        result["relative_poses"],
        result["pose_priors"],
    );
    out += &format!(
        "APE translation (m)      {}\n",
        statistics(&result["ape_trans"])
    );
    out += &format!(
        "APE full (unit-less)     {}\n",
        statistics(&result["ape_full"])
    );
    if !result["ape_smoothed_trans"].is_null() {
        out += &format!(
            "lag-smoothed APE trans.  {}\n",
            statistics(&result["ape_smoothed_trans"])
        );
    }
    out += &format!(
        "update (ms)              {}\n",
        percentiles(&result["update_ms"])
    );
    if !result["latency_ms"].is_null() {
        out += &format!(
            "latency (ms)             {}\n",
            percentiles(&result["latency_ms"])
        );
    }
    out += &format!(
        "Gauss-Newton steps per keyframe (mean) {:.2}\n",
        number(&result["iterations_mean"])
    );
    out
}
