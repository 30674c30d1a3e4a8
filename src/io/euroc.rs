//! EuRoC MAV data as the repository's data directory holds it: `imu0.csv`
//! (`timestamp [ns], w_x, w_y, w_z, a_x, a_y, a_z`, gyroscope first) and a ground truth in TUM
//! format (`t x y z qx qy qz qw`, seconds).
//!
//! Times are returned in seconds from `origin`, a whole second at or before the first IMU
//! sample (the differences are formed in integer nanoseconds first, so 200 Hz steps keep their
//! full precision; raw EuRoC stamps exceed what an f64 holds to the nanosecond).

use std::path::Path;

use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use super::IoError;

#[derive(Clone, Debug)]
pub struct ImuSample {
    pub t: f64,
    pub accel: Vector3<f64>,
    pub gyro: Vector3<f64>,
}

#[derive(Clone, Debug)]
pub struct TruthPose {
    pub t: f64,
    pub position: Vector3<f64>,
    pub rotation: UnitQuaternion<f64>,
}

#[derive(Clone, Debug)]
pub struct Euroc {
    /// Whole seconds (Unix time) subtracted from every time stamp.
    pub origin: i64,
    pub imu: Vec<ImuSample>,
    pub truth: Vec<TruthPose>,
}

fn parse_error(path: &Path, line: usize, reason: impl Into<String>) -> IoError {
    IoError::Parse {
        file: path.to_path_buf(),
        line,
        reason: reason.into(),
    }
}

fn read(path: &Path) -> Result<String, IoError> {
    super::read_text(path).map(|text| super::without_bom(&text).to_string())
}

fn finite_numbers<'a>(
    path: &Path,
    line: usize,
    fields: impl Iterator<Item = &'a str>,
    count: usize,
) -> Result<Vec<f64>, IoError> {
    let values: Vec<f64> = fields
        .map(|f| f.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| parse_error(path, line, format!("not a number: {e}")))?;
    if values.len() != count {
        return Err(parse_error(
            path,
            line,
            format!("expected {count} numbers, found {}", values.len()),
        ));
    }
    if values.iter().any(|v| !v.is_finite()) {
        return Err(parse_error(path, line, "a value is not finite"));
    }
    Ok(values)
}

/// Loads `imu0.csv` and the TUM ground truth `truth` from `dir`.
pub fn load(dir: &Path, truth: &str) -> Result<Euroc, IoError> {
    let imu_path = dir.join("imu0.csv");
    let mut origin = None;
    let mut imu = Vec::new();
    for (index, line) in read(&imu_path)?.lines().enumerate() {
        if line.starts_with('#') || line.trim().is_empty() {
            continue;
        }
        let mut fields = line.split(',');
        let stamp = fields.next().unwrap_or("");
        let ns: i64 = stamp
            .trim()
            .parse()
            .map_err(|e| parse_error(&imu_path, index + 1, format!("time stamp `{stamp}`: {e}")))?;
        let origin = *origin.get_or_insert(ns.div_euclid(1_000_000_000));
        let v = finite_numbers(&imu_path, index + 1, fields, 6)?;
        imu.push(ImuSample {
            t: (ns - origin * 1_000_000_000) as f64 / 1e9,
            gyro: Vector3::new(v[0], v[1], v[2]),
            accel: Vector3::new(v[3], v[4], v[5]),
        });
    }
    let origin = origin.ok_or_else(|| IoError::Invalid {
        file: imu_path.clone(),
        reason: "no IMU samples".into(),
    })?;
    if let Some(k) = imu.windows(2).position(|w| w[1].t <= w[0].t) {
        return Err(IoError::Invalid {
            file: imu_path,
            reason: format!("IMU sample {} is not after the one before it", k + 1),
        });
    }
    let truth_path = dir.join(truth);
    let mut poses = Vec::new();
    for (index, line) in read(&truth_path)?.lines().enumerate() {
        if line.starts_with('#') || line.trim().is_empty() {
            continue;
        }
        let v = finite_numbers(&truth_path, index + 1, line.split_whitespace(), 8)?;
        poses.push(TruthPose {
            t: v[0] - origin as f64,
            position: Vector3::new(v[1], v[2], v[3]),
            rotation: UnitQuaternion::from_quaternion(Quaternion::new(v[7], v[4], v[5], v[6])),
        });
    }
    Ok(Euroc {
        origin,
        imu,
        truth: poses,
    })
}
