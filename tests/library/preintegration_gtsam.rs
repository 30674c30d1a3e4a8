//! IMU pre-integration against GTSAM 4.3's `PreintegratedCombinedMeasurementsManifold` on real
//! EuRoC samples: ΔR, Δv, Δp, Δt, the 15×15 covariance and the five bias Jacobians agree to
//! 1e-9 relative. GTSAM runs from Python (`benches/fusion/gtsam_preintegration.py`) in the venv
//! `~/.cache/factord/venvs/gtsam`, which this test creates on first use.

use crate::common;

use std::io::Write;
use std::path::PathBuf;
use std::process::{Command, Stdio};

use factord::factors::ImuFactor;
use factord::geometry::preintegration::{ImuNoise, Preintegrated};
use nalgebra::{Matrix3, Vector3};
use serde_json::Value;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// (t in ns, accelerometer, gyroscope) per line of imu0.csv.
fn samples(path: &std::path::Path) -> Vec<(i64, Vector3<f64>, Vector3<f64>)> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            let v: Vec<f64> = f[1..7].iter().map(|x| x.trim().parse().unwrap()).collect();
            (
                f[0].trim().parse().unwrap(),
                Vector3::new(v[3], v[4], v[5]),
                Vector3::new(v[0], v[1], v[2]),
            )
        })
        .collect()
}

fn numbers(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

/// Every entry within 1e-9 of GTSAM's, relative to the largest entry of that quantity.
fn assert_agrees(what: &str, ours: &[f64], gtsam: &[f64]) {
    assert_eq!(ours.len(), gtsam.len(), "{what}");
    let scale = gtsam.iter().fold(0.0f64, |m, v| m.max(v.abs())).max(1e-300);
    let worst = ours
        .iter()
        .zip(gtsam)
        .map(|(a, b)| (a - b).abs() / scale)
        .fold(0.0f64, f64::max);
    println!("{what}: worst relative difference {worst:.2e}");
    assert!(worst <= 1e-9, "{what}: relative difference {worst:.3e}");
}

fn row_major(m: &Matrix3<f64>) -> Vec<f64> {
    (0..3)
        .flat_map(|r| (0..3).map(move |c| m[(r, c)]))
        .collect()
}

#[test]
fn preintegration_matches_gtsam_manifold() {
    let Some(imu_path) = common::data_file("imu/euroc_V1_01_easy/imu0.csv") else {
        return;
    };
    let Some(python) = common::gtsam_python() else {
        return;
    };
    let noise = ImuNoise::EUROC;
    let (bias_acc, bias_gyro) = (
        Vector3::new(-0.025, 0.136, 0.075),
        Vector3::new(-0.002, 0.021, 0.076),
    );
    let intervals = [(1000, 20), (1020, 20), (5000, 200), (20000, 37)];
    let request = serde_json::json!({
        "data_dir": imu_path.parent().unwrap(),
        "backend": "manifold",
        "gravity": 9.81,
        "noise": {
            "accelerometer_noise_density": noise.accel_noise_density,
            "gyroscope_noise_density": noise.gyro_noise_density,
            "accelerometer_random_walk": noise.accel_random_walk,
            "gyroscope_random_walk": noise.gyro_random_walk,
            "integration_sigma": noise.integration_sigma,
        },
        "bias": {"acc": bias_acc.as_slice(), "gyro": bias_gyro.as_slice()},
        "intervals": intervals
            .iter()
            .map(|&(s, n)| serde_json::json!({"start_index": s, "count": n}))
            .collect::<Vec<_>>(),
        "factor_intervals": [],
    });
    let mut child = Command::new(&python)
        .arg(repo().join("benches/fusion/gtsam_preintegration.py"))
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    child
        .stdin
        .take()
        .unwrap()
        .write_all(request.to_string().as_bytes())
        .unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let reply: Value = serde_json::from_slice(&out.stdout).unwrap();
    let results = reply["results"]["manifold"].as_array().unwrap();
    assert_eq!(results.len(), intervals.len());
    let data = samples(&imu_path);
    for (&(start, count), g) in intervals.iter().zip(results) {
        let mut ours = Preintegrated::new(noise, bias_acc, bias_gyro);
        for k in start..start + count {
            let dt = (data[k + 1].0 - data[k].0) as f64 / 1e9;
            ours.integrate(&data[k].1, &data[k].2, dt);
        }
        let what = |q: &str| format!("interval {start}+{count}: {q}");
        assert_eq!(
            g["t_start_ns"].as_i64().unwrap(),
            data[start].0,
            "{}",
            what("start")
        );
        assert_agrees(
            &what("Δt"),
            &[ours.delta_t],
            &[g["deltaTij"].as_f64().unwrap()],
        );
        assert_agrees(
            &what("ΔR"),
            &row_major(&ours.delta_rotation),
            &numbers(&g["deltaRij"]),
        );
        assert_agrees(
            &what("Δv"),
            ours.delta_velocity.as_slice(),
            &numbers(&g["deltaVij"]),
        );
        assert_agrees(
            &what("Δp"),
            ours.delta_position.as_slice(),
            &numbers(&g["deltaPij"]),
        );
        let covariance: Vec<f64> = (0..15)
            .flat_map(|r| (0..15).map(move |c| (r, c)))
            .map(|(r, c)| ours.covariance[(r, c)])
            .collect();
        assert_agrees(
            &what("covariance"),
            &covariance,
            &numbers(&g["preintMeasCov"]),
        );
        // The factor's residual covariance: ours, mapped back to GTSAM's order (position and
        // rotation blocks swapped), is GTSAM's residualCovariance (cross blocks with the biases
        // change sign).
        let residual =
            ImuFactor::new(0, 1, ours.clone(), Vector3::new(0.0, 0.0, -9.81)).covariance();
        let gtsam_to_ours = |k: usize| match k / 3 {
            0 => 3 + k % 3,
            1 => k % 3,
            _ => k,
        };
        let residual: Vec<f64> = (0..15)
            .flat_map(|r| (0..15).map(move |c| (r, c)))
            .map(|(r, c)| residual[(gtsam_to_ours(r), gtsam_to_ours(c))])
            .collect();
        assert_agrees(
            &what("residual covariance"),
            &residual,
            &numbers(&g["residualCovariance"]),
        );
        for (name, m) in [
            ("delRdelBiasOmega", &ours.d_rotation_d_gyro_bias),
            ("delPdelBiasAcc", &ours.d_position_d_accel_bias),
            ("delPdelBiasOmega", &ours.d_position_d_gyro_bias),
            ("delVdelBiasAcc", &ours.d_velocity_d_accel_bias),
            ("delVdelBiasOmega", &ours.d_velocity_d_gyro_bias),
        ] {
            assert_agrees(&what(name), &row_major(m), &numbers(&g[name]));
        }
    }
}
