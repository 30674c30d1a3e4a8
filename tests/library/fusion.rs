//! The sliding-window estimator on real EuRoC V1_01 IMU data: keyframes at 10 Hz, lidar-like
//! relative poses and 1 Hz map-matching priors made from the ground truth with known noise
//! (`eval/experiment.rs`), and its refusals of bad input.

use crate::common;

use crate::common::eval::experiment::{self, Generation};
use factord::fusion::window::{FusionError, SlidingWindow, WindowOptions};
use factord::geometry::NavState;
use factord::io::euroc;
use nalgebra::{DMatrix, UnitQuaternion, Vector3};

fn diagonal(values: &[f64]) -> DMatrix<f64> {
    DMatrix::from_diagonal(&nalgebra::DVector::from_column_slice(values))
}

/// APE (translation, RMSE) of the newest state over the first 20 s, for the given factors.
fn ape(window: usize, use_imu: bool, priors: bool) -> Option<f64> {
    let imu = common::data_file("imu/euroc_V1_01_easy/imu0.csv")?;
    let data = euroc::load(imu.parent().unwrap(), "groundtruth_20hz_tum.txt").unwrap();
    let generation = Generation {
        seconds: 20.0,
        window,
        use_imu,
        prior_every: if priors { 10 } else { 0 },
        ..Generation::default()
    };
    let inputs = experiment::generate(&data, &generation).unwrap();
    // What the GTSAM script reads survives a round trip through JSON (serde_json may parse a
    // float one ulp off, so equality is up to that).
    let text = serde_json::to_string(&inputs).unwrap();
    let back: experiment::FusionInputs = serde_json::from_str(&text).unwrap();
    assert_eq!(back.keyframes.len(), inputs.keyframes.len());
    assert_eq!(back.imu.len(), inputs.imu.len());
    for (a, b) in back.imu.iter().zip(&inputs.imu) {
        assert!(a
            .iter()
            .zip(b)
            .all(|(x, y)| (x - y).abs() <= 1e-15 * y.abs().max(1.0)));
    }
    let estimates = experiment::run(&inputs).unwrap();
    assert_eq!(estimates.len(), 200);
    let tum = experiment::tum(&inputs, &estimates);
    assert_eq!(tum.lines().count(), 201);
    let (full, trans) = experiment::ape(&inputs, &estimates);
    assert!(full.rmse >= trans.rmse * 0.9 && full.min <= full.median && full.median <= full.max);
    Some(trans.rmse)
}

#[test]
fn window_tracks_euroc_with_imu_lidar_and_map_priors() {
    let Some(fused) = ape(10, true, true) else {
        return;
    };
    let no_priors = ape(10, true, false).unwrap();
    let small_window = ape(2, true, true).unwrap();
    eprintln!("APE rmse over 20 s: fused {fused:.4} m, without priors {no_priors:.4} m, window 2 {small_window:.4} m");
    // Better than the map priors themselves (σ = 0.1 m per axis: 0.17 m RMS).
    assert!(fused < 0.15, "fused APE rmse {fused}");
    // Without absolute fixes the position drifts.
    assert!(
        no_priors > 1.5 * fused,
        "without priors {no_priors} vs {fused}"
    );
    // Marginalisation keeps what the old keyframes said: a short window loses almost nothing.
    assert!(
        (small_window - fused).abs() < 0.1 * fused,
        "{small_window} vs {fused}"
    );
}

/// The lag-smoothed trajectory: every keyframe once (the initial state included), in time
/// order, each as it left the window, and closer to the truth than the real-time estimate (it
/// saw the window's later measurements too).
#[test]
fn keyframes_leaving_the_window_are_lag_smoothed() {
    let Some(imu) = common::data_file("imu/euroc_V1_01_easy/imu0.csv") else {
        return;
    };
    let data = euroc::load(imu.parent().unwrap(), "groundtruth_20hz_tum.txt").unwrap();
    let inputs = experiment::generate(
        &data,
        &Generation {
            seconds: 20.0,
            window: 10,
            ..Generation::default()
        },
    )
    .unwrap();
    let (real_time, smoothed) = experiment::run_smoothed(&inputs).unwrap();
    let plain = experiment::run(&inputs).unwrap();
    assert!(plain
        .iter()
        .zip(&real_time)
        .all(|(a, b)| a.key == b.key && a.pose == b.pose));
    assert_eq!(
        smoothed.len(),
        real_time.len() + 1,
        "every keyframe and the initial state"
    );
    assert!(smoothed
        .windows(2)
        .all(|w| w[0].t < w[1].t && w[0].key != w[1].key));
    // The newest keyframe's smoothed estimate is its real-time one (nothing came after it).
    let (last, newest) = (smoothed.last().unwrap(), real_time.last().unwrap());
    assert_eq!((last.key, &last.pose), (newest.key, &newest.pose));
    let (_, trans) = experiment::ape(&inputs, &real_time);
    let (_, smoothed_trans) = experiment::ape(&inputs, &smoothed);
    eprintln!(
        "APE rmse over 20 s, window 10: real-time {:.4} m, lag-smoothed {:.4} m",
        trans.rmse, smoothed_trans.rmse
    );
    assert!(
        smoothed_trans.rmse < trans.rmse,
        "{} vs {}",
        smoothed_trans.rmse,
        trans.rmse
    );
}

#[test]
fn bad_fusion_input_is_refused_and_the_window_stays_intact() {
    let information = DMatrix::identity(15, 15);
    let first = NavState::at_pose(&factord::geometry::Se3::identity());
    let mut w = SlidingWindow::new(WindowOptions::default(), first, 0.0, &information).unwrap();
    let g = Vector3::new(0.0, 0.0, 9.81);
    let z = Vector3::zeros();
    assert!(matches!(
        w.add_keyframe(0.1),
        Err(FusionError::KeyframeWithoutImu { .. })
    ));
    w.add_imu(0.01, g, z).unwrap();
    assert!(matches!(
        w.add_imu(0.01, g, z),
        Err(FusionError::ImuOutOfOrder { .. })
    ));
    assert!(matches!(
        w.add_imu(0.005, g, z),
        Err(FusionError::ImuOutOfOrder { .. })
    ));
    assert!(matches!(
        w.add_imu(0.02, Vector3::new(f64::NAN, 0.0, 0.0), z),
        Err(FusionError::ImuNotFinite { .. })
    ));
    w.add_imu(0.02, g, z).unwrap();
    let k1 = w.add_keyframe(0.1).unwrap();
    assert!(matches!(
        w.add_keyframe(0.05),
        Err(FusionError::KeyframeOutOfOrder { .. })
    ));
    assert!(matches!(
        w.add_imu(0.05, g, z),
        Err(FusionError::ImuBeforeKeyframe { .. })
    ));
    let pose = diagonal(&[1.0; 6]);
    assert!(matches!(
        w.add_pose_prior(7, z, UnitQuaternion::identity(), &pose),
        Err(FusionError::NotInWindow { key: 7 })
    ));
    assert!(matches!(
        w.add_pose_prior(k1, z, UnitQuaternion::identity(), &diagonal(&[1.0; 3])),
        Err(FusionError::Invalid { .. })
    ));
    // Nothing refused changed the window: one IMU factor between the two keyframes.
    assert_eq!(w.window().len(), 2);
    assert_eq!(w.problem().factors().len(), 2);
    // Marginalised keyframes refuse priors too.
    let options = WindowOptions {
        size: 2,
        ..WindowOptions::default()
    };
    let mut w = SlidingWindow::new(options, first, 0.0, &information).unwrap();
    for k in 1..=3 {
        w.add_imu(0.1 * k as f64 - 0.05, g, z).unwrap();
        w.add_keyframe(0.1 * k as f64).unwrap();
        w.optimize().unwrap();
    }
    assert!(matches!(
        w.add_pose_prior(0, z, UnitQuaternion::identity(), &pose),
        Err(FusionError::NotInWindow { key: 0 })
    ));
    assert_eq!(w.window().len(), 2);
}

/// A keyframe from deltas pre-integrated on the robot equals one from the raw samples.
#[test]
fn preintegrated_deltas_and_raw_samples_give_the_same_keyframe() {
    use factord::geometry::preintegration::{ImuNoise, Preintegrated};
    let information = DMatrix::identity(15, 15) * 100.0;
    let first = NavState::at_pose(&factord::geometry::Se3::identity());
    let samples: Vec<(f64, Vector3<f64>, Vector3<f64>)> = (1..=20)
        .map(|k| {
            let t = 0.005 * k as f64;
            let s = t * 7.0;
            (
                t,
                Vector3::new(0.3 * s.sin(), 0.1, 9.81 + 0.2 * s.cos()),
                Vector3::new(0.01, -0.02 * s, 0.05),
            )
        })
        .collect();
    let mut raw = SlidingWindow::new(WindowOptions::default(), first, 0.0, &information).unwrap();
    // The window holds sample k from t_k to t_{k+1} (and the first one from the keyframe).
    let mut on_robot = Preintegrated::new(ImuNoise::EUROC, Vector3::zeros(), Vector3::zeros());
    let mut previous: Option<(f64, Vector3<f64>, Vector3<f64>)> = None;
    for &(t, acc, gyro) in &samples {
        raw.add_imu(t, acc, gyro).unwrap();
        if let Some((tp, a, w)) = previous {
            on_robot.integrate(&a, &w, t - tp);
        }
        previous = Some((t, acc, gyro));
    }
    let end = 0.105;
    let (tp, a, w) = previous.unwrap();
    on_robot.integrate(&a, &w, end - tp);
    let a_key = raw.add_keyframe(end).unwrap();
    // The robot's integration starts at its first sample (0.005 s): a window whose previous
    // keyframe is at 0 refuses the 0.1 s it spans, one whose keyframe is at 0.005 takes it.
    let mut early = SlidingWindow::new(WindowOptions::default(), first, 0.0, &information).unwrap();
    assert!(matches!(
        early.add_keyframe_preintegrated(end, on_robot.clone()),
        Err(FusionError::Invalid {
            field: "delta_t",
            ..
        })
    ));
    let mut delta =
        SlidingWindow::new(WindowOptions::default(), first, 0.005, &information).unwrap();
    let b_key = delta.add_keyframe_preintegrated(end, on_robot).unwrap();
    let (a, b) = (raw.state(a_key).unwrap(), delta.state(b_key).unwrap());
    assert!((a.position - b.position).norm() < 1e-12 && (a.velocity - b.velocity).norm() < 1e-12);
    assert!(matches!(
        delta.add_keyframe_preintegrated(
            0.2,
            Preintegrated::new(ImuNoise::EUROC, Vector3::zeros(), Vector3::zeros())
        ),
        Err(FusionError::KeyframeWithoutImu { .. })
    ));
}

/// The APE statistics are evo's (min, max, median, mean, SSE, RMSE, standard deviation).
#[test]
fn statistics_are_evos() {
    let s = experiment::ErrorStatistics::of(&[1.0, 2.0, 4.0, 3.0]);
    assert_eq!((s.min, s.max, s.median, s.mean), (1.0, 4.0, 2.5, 2.5));
    assert_eq!(s.sse, 30.0);
    assert!((s.rmse - 7.5f64.sqrt()).abs() < 1e-15);
    assert!((s.std - 1.25f64.sqrt()).abs() < 1e-15);
}
