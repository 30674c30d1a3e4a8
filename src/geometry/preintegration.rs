//! IMU pre-integration between two keyframes, as GTSAM's `PreintegratedCombinedMeasurements`
//! (manifold pre-integration) computes it, so the two agree to rounding.
//!
//! Each sample (acc, ω) is held over its interval dt (zero-order hold) and corrected by the
//! bias estimate the pre-integration was started with (b̂_a, b̂_g):
//!
//! ```text
//! a = acc − b̂_a,  w = ω − b̂_g
//! Δp ← Δp + Δv dt + ½ ΔR a dt²
//! Δv ← Δv + ΔR a dt
//! ΔR ← ΔR Exp(w dt)
//! ```
//!
//! together with the first-order bias Jacobians (`∂ΔR/∂b_g`, `∂Δv/∂b_a`, `∂Δv/∂b_g`, `∂Δp/∂b_a`,
//! `∂Δp/∂b_g`) that let the factor correct the deltas when the bias estimate moves without
//! integrating again, and the 15×15 covariance of (δθ, δp, δv, δb_a, δb_g) — GTSAM's order.

use nalgebra::{Matrix3, SMatrix, Vector3};

use crate::geometry::so3;

pub type Matrix15 = SMatrix<f64, 15, 15>;

/// Continuous-time IMU noise, as in a Kalibr / EuRoC `sensor.yaml`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImuNoise {
    /// Accelerometer white noise density, m/s²/√Hz.
    pub accel_noise_density: f64,
    /// Gyroscope white noise density, rad/s/√Hz.
    pub gyro_noise_density: f64,
    /// Accelerometer bias random walk, m/s³/√Hz.
    pub accel_random_walk: f64,
    /// Gyroscope bias random walk, rad/s²/√Hz.
    pub gyro_random_walk: f64,
    /// Position-integration noise, m/s/√Hz (GTSAM's integrationCovariance). Without it one
    /// sample's position and velocity noise come from the same accelerometer noise and their
    /// joint covariance is singular; 1e-4 is GTSAM's examples' value.
    #[serde(default = "default_integration_sigma")]
    pub integration_sigma: f64,
}

fn default_integration_sigma() -> f64 {
    1e-4
}

impl ImuNoise {
    /// EuRoC's ADIS16448 (`imu0_sensor.yaml` of the MAV datasets).
    pub const EUROC: ImuNoise = ImuNoise {
        accel_noise_density: 2.0e-3,
        gyro_noise_density: 1.6968e-4,
        accel_random_walk: 3.0e-3,
        gyro_random_walk: 1.9393e-5,
        integration_sigma: 1e-4,
    };

    pub fn validate(&self) -> Result<(), String> {
        for (name, v) in [
            ("accel_noise_density", self.accel_noise_density),
            ("gyro_noise_density", self.gyro_noise_density),
            ("accel_random_walk", self.accel_random_walk),
            ("gyro_random_walk", self.gyro_random_walk),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{name} must be a finite number > 0, got {v}"));
            }
        }
        if !(self.integration_sigma.is_finite() && self.integration_sigma >= 0.0) {
            return Err(format!(
                "integration_sigma must be a finite number >= 0, got {}",
                self.integration_sigma
            ));
        }
        Ok(())
    }
}

/// The pre-integrated measurement between two keyframes.
#[derive(Clone, Debug, PartialEq)]
pub struct Preintegrated {
    pub noise: ImuNoise,
    /// The bias estimate the samples were corrected with.
    pub accel_bias: Vector3<f64>,
    pub gyro_bias: Vector3<f64>,
    /// Σ dt.
    pub delta_t: f64,
    pub delta_rotation: Matrix3<f64>,
    pub delta_velocity: Vector3<f64>,
    pub delta_position: Vector3<f64>,
    pub d_rotation_d_gyro_bias: Matrix3<f64>,
    pub d_velocity_d_accel_bias: Matrix3<f64>,
    pub d_velocity_d_gyro_bias: Matrix3<f64>,
    pub d_position_d_accel_bias: Matrix3<f64>,
    pub d_position_d_gyro_bias: Matrix3<f64>,
    /// Covariance of (δθ, δp, δv, δb_a, δb_g).
    pub covariance: Matrix15,
    pub samples: usize,
}

impl Preintegrated {
    pub fn new(noise: ImuNoise, accel_bias: Vector3<f64>, gyro_bias: Vector3<f64>) -> Self {
        Self {
            noise,
            accel_bias,
            gyro_bias,
            delta_t: 0.0,
            delta_rotation: Matrix3::identity(),
            delta_velocity: Vector3::zeros(),
            delta_position: Vector3::zeros(),
            d_rotation_d_gyro_bias: Matrix3::zeros(),
            d_velocity_d_accel_bias: Matrix3::zeros(),
            d_velocity_d_gyro_bias: Matrix3::zeros(),
            d_position_d_accel_bias: Matrix3::zeros(),
            d_position_d_gyro_bias: Matrix3::zeros(),
            covariance: Matrix15::zeros(),
            samples: 0,
        }
    }

    /// Adds one sample held for `dt` seconds (dt > 0, finite; checked by the caller).
    pub fn integrate(&mut self, accel: &Vector3<f64>, gyro: &Vector3<f64>, dt: f64) {
        let a = accel - self.accel_bias;
        let w = gyro - self.gyro_bias;
        let r = self.delta_rotation;
        let dt22 = 0.5 * dt * dt;
        let theta = w * dt;
        let incr = so3::exp(&theta).to_rotation_matrix().into_inner();
        let jr = so3::right_jacobian(&theta);
        let ra_hat = r * so3::hat(&a);

        // Covariance first: its Jacobians are at the state before the update.
        self.propagate_covariance(&r, &a, &incr, &jr, dt);

        // Bias Jacobians (GTSAM's recursions), also with the old ΔR.
        let d_acc_d_bg = -(ra_hat * self.d_rotation_d_gyro_bias);
        self.d_position_d_accel_bias += self.d_velocity_d_accel_bias * dt - r * dt22;
        self.d_position_d_gyro_bias += self.d_velocity_d_gyro_bias * dt + d_acc_d_bg * dt22;
        self.d_velocity_d_accel_bias -= r * dt;
        self.d_velocity_d_gyro_bias += d_acc_d_bg * dt;
        self.d_rotation_d_gyro_bias = incr.transpose() * self.d_rotation_d_gyro_bias - jr * dt;

        self.delta_position += self.delta_velocity * dt + r * a * dt22;
        self.delta_velocity += r * a * dt;
        self.delta_rotation = r * incr;
        self.delta_t += dt;
        self.samples += 1;
    }

    /// `P ← F P Fᵀ + Q` for one step, GTSAM's manifold form (benches/fusion/GTSAM_PREINTEGRATION.md
    /// §6–7), in the order (δθ, δp, δv, δb_a, δb_g) with the right-perturbation chart of
    /// (ΔR, Δp, Δv). With δR = Exp(w dt), b_v = ΔRᵀ Δv, ξ_P = b_v dt + ½ a dt², ξ_V = a dt:
    ///
    /// ```text
    /// A = [[δRᵀ, 0, 0], [−δRᵀ[ξ_P]× + dt δRᵀ[b_v]×, δRᵀ, dt δRᵀ], [−δRᵀ[ξ_V]×, 0, δRᵀ]]
    /// B = [0; ½dt² δRᵀ; dt δRᵀ]   C = [J_r(w dt) dt; 0; 0]   F = [[A, B, C], [0, I, 0], [0, 0, I]]
    /// Q = B Σ_a/dt Bᵀ + C Σ_g/dt Cᵀ + dt Σ_i (position) + dt Σ_ba + dt Σ_bg (bias blocks)
    /// ```
    ///
    /// (+B and +C although the samples enter as a − b_a, ω − b_g: GTSAM's sign, which fixes the
    /// sign of the state–bias cross-covariance.)
    fn propagate_covariance(
        &mut self,
        r: &Matrix3<f64>,
        a: &Vector3<f64>,
        incr: &Matrix3<f64>,
        jr: &Matrix3<f64>,
        dt: f64,
    ) {
        let dt22 = 0.5 * dt * dt;
        let incr_t = incr.transpose();
        let body_velocity = r.transpose() * self.delta_velocity;
        let xi_p = body_velocity * dt + a * dt22;
        let xi_v = a * dt;
        let mut f = Matrix15::identity();
        let mut put = |row: usize, col: usize, m: &Matrix3<f64>| {
            f.fixed_view_mut::<3, 3>(row, col).copy_from(m);
        };
        put(0, 0, &incr_t);
        put(
            3,
            0,
            &(-incr_t * so3::hat(&xi_p) + incr_t * so3::hat(&body_velocity) * dt),
        );
        put(3, 3, &incr_t);
        put(3, 6, &(incr_t * dt));
        put(6, 0, &(-incr_t * so3::hat(&xi_v)));
        put(6, 6, &incr_t);
        put(3, 9, &(incr_t * dt22));
        put(6, 9, &(incr_t * dt));
        put(0, 12, &(jr * dt));
        let n = &self.noise;
        let (sa, sg) = (
            n.accel_noise_density * n.accel_noise_density / dt,
            n.gyro_noise_density * n.gyro_noise_density / dt,
        );
        let (b1, b2, c0) = (incr_t * dt22, incr_t * dt, jr * dt);
        let mut q = Matrix15::zeros();
        let mut put_q = |row: usize, col: usize, m: &Matrix3<f64>| {
            q.fixed_view_mut::<3, 3>(row, col).copy_from(m);
        };
        put_q(0, 0, &(c0 * c0.transpose() * sg));
        put_q(
            3,
            3,
            &(b1 * b1.transpose() * sa
                + Matrix3::identity() * (dt * n.integration_sigma * n.integration_sigma)),
        );
        put_q(3, 6, &(b1 * b2.transpose() * sa));
        put_q(6, 3, &(b2 * b1.transpose() * sa));
        put_q(6, 6, &(b2 * b2.transpose() * sa));
        put_q(
            9,
            9,
            &(Matrix3::identity() * (dt * n.accel_random_walk * n.accel_random_walk)),
        );
        put_q(
            12,
            12,
            &(Matrix3::identity() * (dt * n.gyro_random_walk * n.gyro_random_walk)),
        );
        let p = f * self.covariance * f.transpose() + q;
        self.covariance = (p + p.transpose()) * 0.5;
    }
}
