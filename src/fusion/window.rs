//! The sliding-window estimator: keyframes joined by pre-integrated IMU factors, relative-pose
//! (lidar odometry) factors and absolute priors (map matching, GNSS); at most `size`
//! keyframes stay free, older ones are marginalised into a prior.
//!
//! IMU samples are held until the next one (zero-order hold, as GTSAM's pre-integration): a
//! keyframe at time t closes the pre-integration with the last sample held up to t, and the
//! next pre-integration starts at t with that same sample.

use std::collections::VecDeque;

use nalgebra::{DMatrix, DVector, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use super::gauss_newton::{Outcome, WindowSolver, WindowUpdate};
use super::marginalize::{marginalize, MarginalizeError};
use crate::factors::{ImuFactor, MarginalPrior, PosePriorNav, PositionPriorNav, RelativePoseNav};
use crate::geometry::preintegration::{ImuNoise, Preintegrated};
use crate::geometry::NavState;
use crate::problem::{Key, Problem, ProblemError};
use crate::solver::{optimize, Initialization, Method, SolverError, SolverOptions};

/// The largest window: a window that never fills never marginalises, and its solve grows with
/// every keyframe (a client's `window` of 2^64 - 1 was accepted once).
pub const MAX_WINDOW: usize = 1000;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WindowOptions {
    /// Keyframes kept free (2 ≤ N ≤ [`MAX_WINDOW`]).
    pub size: usize,
    /// Gravity magnitude, m/s²; the world's z axis points up.
    pub gravity: f64,
    pub imu_noise: ImuNoise,
    pub solver: SolverOptions,
    /// Gauss-Newton: a keyframe's update ends after a step whose actual decrease of chi2
    /// differed from the quadratic model's prediction by at most this (about what a further
    /// step would still gain); the next keyframe's step takes the rest, as a fixed-lag smoother
    /// that takes one step per keyframe does. 0: iterate to the solver's tolerances at every
    /// keyframe. The default (0.01, i.e. the estimate within about 0.1 σ of the window's
    /// optimum in its least certain direction) takes one step at 99.6 % of EuRoC V1_01's
    /// keyframes and moves the APE by at most 3e-7 m (windows of 10 and 20).
    #[serde(default = "default_deferred_chi2")]
    pub deferred_chi2: f64,
}

fn default_deferred_chi2() -> f64 {
    0.01
}

/// Gauss-Newton by default: with the IMU every direction of a keyframe is observed, and from
/// the previous optimum plus a dead-reckoned keyframe it converges in about two iterations
/// (LM took eleven on EuRoC with the same result).
impl Default for WindowOptions {
    fn default() -> Self {
        Self {
            size: 10,
            gravity: 9.81,
            imu_noise: ImuNoise::EUROC,
            solver: SolverOptions {
                method: Method::GaussNewton,
                max_iterations: 20,
                initialization: Initialization::None,
                ..SolverOptions::default()
            },
            deferred_chi2: default_deferred_chi2(),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum FusionError {
    #[error("IMU sample at t = {t}: not after the previous sample (t = {previous})")]
    ImuOutOfOrder { t: f64, previous: f64 },
    #[error("IMU sample at t = {t}: a value is not finite")]
    ImuNotFinite { t: f64 },
    #[error("IMU sample at t = {t}: before the last keyframe (t = {keyframe})")]
    ImuBeforeKeyframe { t: f64, keyframe: f64 },
    #[error("keyframe at t = {t}: not after the previous keyframe (t = {previous})")]
    KeyframeOutOfOrder { t: f64, previous: f64 },
    #[error("keyframe at t = {t}: no IMU sample since the previous keyframe (t = {previous})")]
    KeyframeWithoutImu { t: f64, previous: f64 },
    #[error("keyframe {key} is not in the window (marginalised, or never created)")]
    NotInWindow { key: Key },
    #[error("{field}: {reason}")]
    Invalid { field: &'static str, reason: String },
    #[error(transparent)]
    Problem(#[from] ProblemError),
    #[error(transparent)]
    Solver(#[from] SolverError),
    #[error(transparent)]
    Marginalize(#[from] MarginalizeError),
}

#[derive(Debug)]
pub struct SlidingWindow {
    pub options: WindowOptions,
    problem: Problem,
    /// Free keyframes, oldest first: key and time.
    keyframes: VecDeque<(Key, f64)>,
    /// Pre-integration since the newest keyframe, and the last sample (time, acc, gyro).
    pending: Preintegrated,
    last_sample: Option<(f64, Vector3<f64>, Vector3<f64>)>,
    /// Samples received since the newest keyframe.
    samples_since_keyframe: usize,
    next_key: Key,
    /// The Gauss-Newton solve's buffers, kept between keyframes.
    solver: WindowSolver,
    /// The keyframes the last [`SlidingWindow::optimize`] marginalised, with their estimate at
    /// that optimum: the lag-smoothed states (each saw every measurement of the window it
    /// leaves).
    departed: Vec<(Key, f64, NavState)>,
}

/// The diagonal information of independent measurements: `1/σ²` for each (σ, count).
pub fn diagonal_information(sigmas: &[(f64, usize)]) -> Result<DMatrix<f64>, FusionError> {
    let mut values = Vec::new();
    for &(s, n) in sigmas {
        if !(s.is_finite() && s > 0.0) {
            return Err(FusionError::Invalid {
                field: "sigma",
                reason: format!("must be a finite number > 0, got {s}"),
            });
        }
        values.extend(std::iter::repeat_n(1.0 / (s * s), n));
    }
    Ok(DMatrix::from_diagonal(&nalgebra::DVector::from_vec(values)))
}

/// A rotation from a Hamilton quaternion written x y z w (normalised).
pub fn quaternion_xyzw(q: &[f64; 4]) -> UnitQuaternion<f64> {
    UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[3], q[0], q[1], q[2]))
}

fn check_information(field: &'static str, m: &DMatrix<f64>, dim: usize) -> Result<(), FusionError> {
    if m.nrows() != dim || m.ncols() != dim {
        return Err(FusionError::Invalid {
            field,
            reason: format!("expected {dim}×{dim}, got {}×{}", m.nrows(), m.ncols()),
        });
    }
    Ok(())
}

impl SlidingWindow {
    /// Starts with keyframe 0 at `t0` in state `first`, held by a prior of `information`
    /// (15×15, tangent order (p, θ, v, b_a, b_g)).
    pub fn new(
        options: WindowOptions,
        first: NavState,
        t0: f64,
        information: &DMatrix<f64>,
    ) -> Result<Self, FusionError> {
        if !(2..=MAX_WINDOW).contains(&options.size) {
            return Err(FusionError::Invalid {
                field: "size",
                reason: format!(
                    "the window holds 2 to {MAX_WINDOW} keyframes, got {}",
                    options.size
                ),
            });
        }
        if !(options.gravity.is_finite() && options.gravity > 0.0) {
            return Err(FusionError::Invalid {
                field: "gravity",
                reason: format!("must be a finite number > 0, got {}", options.gravity),
            });
        }
        if !(options.deferred_chi2.is_finite() && options.deferred_chi2 >= 0.0) {
            return Err(FusionError::Invalid {
                field: "deferred_chi2",
                reason: format!(
                    "must be a finite number >= 0, got {}",
                    options.deferred_chi2
                ),
            });
        }
        options
            .imu_noise
            .validate()
            .map_err(|reason| FusionError::Invalid {
                field: "imu_noise",
                reason,
            })?;
        check_information("information", information, 15)?;
        let mut problem = Problem::new();
        problem.add_variable(0, Box::new(first))?;
        let sqrt = information
            .clone()
            .cholesky()
            .ok_or(FusionError::Invalid {
                field: "information",
                reason: "not positive definite".into(),
            })?
            .l()
            .transpose();
        let prior = MarginalPrior::new(vec![0], vec![Box::new(first)], sqrt, DVector::zeros(15));
        problem.add_factor(
            Box::new(prior),
            &DMatrix::identity(15, 15),
            None,
            "initial state",
        )?;
        let pending = Preintegrated::new(options.imu_noise, first.accel_bias, first.gyro_bias);
        Ok(Self {
            options,
            problem,
            keyframes: VecDeque::from([(0, t0)]),
            pending,
            last_sample: None,
            samples_since_keyframe: 0,
            next_key: 1,
            solver: WindowSolver::default(),
            departed: Vec::new(),
        })
    }

    fn gravity(&self) -> Vector3<f64> {
        Vector3::new(0.0, 0.0, -self.options.gravity)
    }

    fn newest(&self) -> (Key, f64) {
        *self.keyframes.back().expect("the window is never empty")
    }

    pub fn state(&self, key: Key) -> Option<NavState> {
        self.problem.values.get_as::<NavState>(key).copied()
    }

    /// The free keyframes, oldest first: (key, time, state).
    pub fn window(&self) -> Vec<(Key, f64, NavState)> {
        self.keyframes
            .iter()
            .map(|&(k, t)| (k, t, self.state(k).expect("window keys hold states")))
            .collect()
    }

    pub fn latest(&self) -> (Key, f64, NavState) {
        let (k, t) = self.newest();
        (k, t, self.state(k).expect("window keys hold states"))
    }

    pub fn problem(&self) -> &Problem {
        &self.problem
    }

    /// One IMU sample (accelerometer m/s², gyroscope rad/s, body frame) at time `t` seconds.
    pub fn add_imu(
        &mut self,
        t: f64,
        accel: Vector3<f64>,
        gyro: Vector3<f64>,
    ) -> Result<(), FusionError> {
        if !(t.is_finite() && accel.iter().chain(gyro.iter()).all(|v| v.is_finite())) {
            return Err(FusionError::ImuNotFinite { t });
        }
        let (_, keyframe_t) = self.newest();
        if t < keyframe_t {
            return Err(FusionError::ImuBeforeKeyframe {
                t,
                keyframe: keyframe_t,
            });
        }
        if let Some((previous, a, w)) = self.last_sample {
            if t <= previous {
                return Err(FusionError::ImuOutOfOrder { t, previous });
            }
            let start = previous.max(keyframe_t);
            if t > start {
                self.pending.integrate(&a, &w, t - start);
            }
        }
        self.last_sample = Some((t, accel, gyro));
        self.samples_since_keyframe += 1;
        Ok(())
    }

    /// Creates the keyframe at time `t` from the IMU samples since the previous one; returns
    /// its key. Its state is predicted by dead reckoning from the previous keyframe.
    pub fn add_keyframe(&mut self, t: f64) -> Result<Key, FusionError> {
        let previous_t = self.check_keyframe_time(t)?;
        let Some((sample_t, a, w)) = self.last_sample.filter(|_| self.samples_since_keyframe > 0)
        else {
            return Err(FusionError::KeyframeWithoutImu {
                t,
                previous: previous_t,
            });
        };
        if t < sample_t {
            return Err(FusionError::KeyframeOutOfOrder {
                t,
                previous: sample_t,
            });
        }
        // Hold the last sample up to the keyframe.
        let mut preintegrated = self.pending.clone();
        let start = sample_t.max(previous_t);
        if t > start {
            preintegrated.integrate(&a, &w, t - start);
        }
        self.push_imu_keyframe(t, preintegrated)
    }

    /// Creates the keyframe at time `t` from a measurement pre-integrated elsewhere (a robot
    /// that integrates on board), since the previous keyframe; the window's own IMU samples
    /// are not used. Its Δt must match the keyframe interval to a microsecond.
    pub fn add_keyframe_preintegrated(
        &mut self,
        t: f64,
        preintegrated: Preintegrated,
    ) -> Result<Key, FusionError> {
        let previous_t = self.check_keyframe_time(t)?;
        if preintegrated.samples == 0 {
            return Err(FusionError::KeyframeWithoutImu {
                t,
                previous: previous_t,
            });
        }
        if (preintegrated.delta_t - (t - previous_t)).abs() > 1e-6 {
            return Err(FusionError::Invalid {
                field: "delta_t",
                reason: format!(
                    "the pre-integration spans {} s, the keyframes {} s",
                    preintegrated.delta_t,
                    t - previous_t
                ),
            });
        }
        self.push_imu_keyframe(t, preintegrated)
    }

    /// Adds the keyframe state (dead-reckoned) and its IMU factor to the previous keyframe.
    fn push_imu_keyframe(
        &mut self,
        t: f64,
        preintegrated: Preintegrated,
    ) -> Result<Key, FusionError> {
        let (previous_key, _) = self.newest();
        let previous = self.state(previous_key).expect("window keys hold states");
        let factor = ImuFactor::new(previous_key, self.next_key, preintegrated, self.gravity());
        let information = factor.information().ok_or(FusionError::Invalid {
            field: "imu",
            reason: "the pre-integration covariance is singular".into(),
        })?;
        let key = self.push_keyframe(t, factor.predict_from(&previous))?;
        self.problem.add_factor(
            Box::new(factor),
            &information,
            None,
            format!("imu {previous_key}-{key}"),
        )?;
        Ok(key)
    }

    /// `t` for a new keyframe: finite and after the newest one, which it returns the time of.
    fn check_keyframe_time(&self, t: f64) -> Result<f64, FusionError> {
        let (_, previous) = self.newest();
        if t.is_finite() && t > previous {
            Ok(previous)
        } else {
            Err(FusionError::KeyframeOutOfOrder { t, previous })
        }
    }

    /// Adds keyframe `state` at `t` to the window; the next pre-integration starts from its
    /// biases (the last IMU sample is held on past it until the next one arrives).
    fn push_keyframe(&mut self, t: f64, state: NavState) -> Result<Key, FusionError> {
        let key = self.next_key;
        self.problem.add_variable(key, Box::new(state))?;
        self.next_key += 1;
        self.keyframes.push_back((key, t));
        self.pending =
            Preintegrated::new(self.options.imu_noise, state.accel_bias, state.gyro_bias);
        self.samples_since_keyframe = 0;
        Ok(key)
    }

    /// A keyframe at time `t` with no IMU factor (a robot without an IMU, or an evaluation of
    /// the other factors alone): its state starts at `guess` and only the relative-pose and
    /// prior factors added next constrain it (velocity and biases stay where LM's damping
    /// holds them, and marginalisation drops them as unobserved).
    pub fn add_keyframe_without_imu(
        &mut self,
        t: f64,
        guess: NavState,
    ) -> Result<Key, FusionError> {
        self.check_keyframe_time(t)?;
        if !guess.is_finite() {
            return Err(FusionError::Invalid {
                field: "guess",
                reason: "not finite".into(),
            });
        }
        self.push_keyframe(t, guess)
    }

    fn require_in_window(&self, key: Key) -> Result<(), FusionError> {
        if self.keyframes.iter().any(|&(k, _)| k == key) {
            Ok(())
        } else {
            Err(FusionError::NotInWindow { key })
        }
    }

    /// Lidar odometry: the pose of `to` in the frame of `from`, with its 6×6 information
    /// (order: position, rotation).
    pub fn add_relative_pose(
        &mut self,
        from: Key,
        to: Key,
        delta_position: Vector3<f64>,
        delta_rotation: UnitQuaternion<f64>,
        information: &DMatrix<f64>,
    ) -> Result<usize, FusionError> {
        self.require_in_window(from)?;
        self.require_in_window(to)?;
        check_information("information", information, 6)?;
        let f = RelativePoseNav::new(from, to, delta_position, delta_rotation);
        Ok(self.problem.add_factor(
            Box::new(f),
            information,
            None,
            format!("relative pose {from}-{to}"),
        )?)
    }

    /// Map matching: the world pose of `key`, with its 6×6 information (position, rotation).
    pub fn add_pose_prior(
        &mut self,
        key: Key,
        position: Vector3<f64>,
        rotation: UnitQuaternion<f64>,
        information: &DMatrix<f64>,
    ) -> Result<usize, FusionError> {
        self.require_in_window(key)?;
        check_information("information", information, 6)?;
        let f = PosePriorNav::new(key, position, rotation);
        Ok(self
            .problem
            .add_factor(Box::new(f), information, None, format!("pose prior {key}"))?)
    }

    /// GNSS: the world position of `key`, with its 3×3 information.
    pub fn add_position_prior(
        &mut self,
        key: Key,
        position: Vector3<f64>,
        information: &DMatrix<f64>,
    ) -> Result<usize, FusionError> {
        self.require_in_window(key)?;
        check_information("information", information, 3)?;
        let f = PositionPriorNav::new(key, position);
        Ok(self.problem.add_factor(
            Box::new(f),
            information,
            None,
            format!("position prior {key}"),
        )?)
    }

    /// Optimises the window, then marginalises the oldest keyframes beyond `size`.
    ///
    /// Gauss-Newton runs on the window's own solver ([`WindowSolver`]); other methods, and
    /// windows it does not take, on the general solver.
    pub fn optimize(&mut self) -> Result<WindowUpdate, FusionError> {
        let mut taken = 0;
        let mut update = None;
        if self.options.solver.method == Method::GaussNewton {
            let keys = self.keyframes.iter().map(|&(k, _)| k);
            match self.solver.solve(
                &mut self.problem,
                keys,
                &self.options.solver,
                self.options.deferred_chi2,
            )? {
                Outcome::Solved(u) => update = Some(u),
                Outcome::General { iterations } => taken = iterations,
            }
        }
        let update = match update {
            Some(u) => u,
            None => {
                let summary = optimize(&mut self.problem, &self.options.solver, &mut |_| {
                    std::ops::ControlFlow::Continue(())
                })?;
                WindowUpdate {
                    iterations: taken + summary.iterations,
                    initial_chi2: summary.initial_chi2,
                    chi2: summary.final_chi2,
                    converged: summary.converged,
                    path: "general",
                }
            }
        };
        self.departed.clear();
        while self.keyframes.len() > self.options.size {
            let (oldest, t) = self.keyframes.pop_front().expect("longer than size ≥ 2");
            if let Some(state) = self.state(oldest) {
                self.departed.push((oldest, t, state));
            }
            marginalize(&mut self.problem, oldest)?;
        }
        Ok(update)
    }

    /// The keyframes the last optimisation marginalised, oldest first, as they left: key,
    /// time and the estimate at that optimisation (lag-smoothed by the window's length).
    pub fn departed(&self) -> &[(Key, f64, NavState)] {
        &self.departed
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::testing::Rng;
    use crate::geometry::{so3, Se3};

    /// A robot turning in place about the vertical at 0.5 rad/s (the accelerometer reads
    /// gravity), keyframes every 0.1 s with noisy relative poses and pose priors on every third;
    /// nothing optimised yet.
    fn turning(options: WindowOptions, keyframes: usize) -> SlidingWindow {
        let mut rng = Rng::new(11);
        let information = DMatrix::identity(15, 15) * 100.0;
        let first = NavState::at_pose(&Se3::identity());
        let mut w = SlidingWindow::new(options, first, 0.0, &information).unwrap();
        let (rate, dt) = (0.5, 0.1);
        let accel = Vector3::new(0.0, 0.0, 9.81);
        let gyro = Vector3::new(0.0, 0.0, rate);
        let pose_information = diagonal_information(&[(0.02, 3), (0.005, 3)]).unwrap();
        let prior_information = diagonal_information(&[(0.1, 3), (0.02, 3)]).unwrap();
        let mut previous = 0;
        for k in 1..=keyframes {
            for s in 0..20 {
                let t = (k - 1) as f64 * dt + (s + 1) as f64 * dt / 20.0;
                w.add_imu(t, accel, gyro + rng.vector3(0.01)).unwrap();
            }
            let key = w.add_keyframe(k as f64 * dt).unwrap();
            let turn = so3::exp(&(Vector3::z() * rate * dt + rng.vector3(0.005)));
            let shift = rng.vector3(0.02);
            w.add_relative_pose(previous, key, shift, turn, &pose_information)
                .unwrap();
            if k % 3 == 0 {
                let yaw = so3::exp(&(Vector3::z() * rate * dt * k as f64 + rng.vector3(0.02)));
                w.add_pose_prior(key, rng.vector3(0.1), yaw, &prior_information)
                    .unwrap();
            }
            previous = key;
        }
        w
    }

    fn tight() -> WindowOptions {
        let mut options = WindowOptions {
            size: 100,
            deferred_chi2: 0.0,
            ..WindowOptions::default()
        };
        options.solver.function_tolerance = 1e-14;
        options.solver.gradient_tolerance = 1e-12;
        options
    }

    /// The window's own Gauss-Newton reaches the general solver's optimum.
    #[test]
    fn window_solve_matches_the_general_solver() {
        let mut ours = turning(tight(), 8);
        let update = ours.optimize().unwrap();
        assert_eq!(update.path, "window");
        assert!(update.converged && update.iterations >= 2, "{update:?}");
        assert!(update.chi2 < update.initial_chi2);
        let mut general = turning(tight(), 8);
        let summary = optimize(&mut general.problem, &general.options.solver, &mut |_| {
            std::ops::ControlFlow::Continue(())
        })
        .unwrap();
        assert!((summary.final_chi2 - update.chi2).abs() <= 1e-9 * update.chi2);
        for ((k, _, a), (_, _, b)) in ours.window().iter().zip(general.window()) {
            let d = a.local(&b);
            assert!(d.amax() < 1e-7, "keyframe {k}: {d}");
        }
    }

    /// A deferred step is one Gauss-Newton step; the next update finishes what it left.
    #[test]
    fn deferral_takes_one_step_and_the_next_update_finishes() {
        let mut lazy = turning(
            WindowOptions {
                deferred_chi2: f64::MAX,
                ..tight()
            },
            8,
        );
        let first = lazy.optimize().unwrap();
        assert_eq!((first.iterations, first.converged), (1, false));
        lazy.options.deferred_chi2 = 0.0;
        let second = lazy.optimize().unwrap();
        assert!(second.converged);
        assert!(second.chi2 <= first.chi2);
        let mut full = turning(tight(), 8);
        let converged = full.optimize().unwrap();
        assert!((second.chi2 - converged.chi2).abs() <= 1e-9 * converged.chi2);
    }

    /// Marginalising at the optimum (here by Cholesky: the IMU observes every direction) keeps
    /// the optimum of the keyframes that stay, wherever they start from.
    #[test]
    fn marginalising_at_the_optimum_keeps_the_optimum() {
        let mut full = turning(tight(), 8);
        full.optimize().unwrap();
        let mut short = turning(WindowOptions { size: 4, ..tight() }, 8);
        short.optimize().unwrap();
        let kept = short.window();
        assert_eq!(kept.len(), 4);
        let marginal = short
            .problem
            .factors()
            .iter()
            .filter(|f| f.factor.name() == "marginal_prior");
        assert_eq!(marginal.count(), 1);
        for &(k, _, _) in &kept {
            let v = short.problem.values.index_of(k).unwrap();
            let mut delta = [0.0; 15];
            delta[0] = 0.05;
            delta[5] = 0.02;
            delta[7] = -0.1;
            short.problem.values.variable_mut(v).retract(&delta);
        }
        let update = short.optimize().unwrap();
        assert_eq!(update.path, "window");
        for (k, _, state) in short.window() {
            let d = state.local(&full.state(k).unwrap());
            assert!(d.amax() < 1e-6, "keyframe {k}: {d}");
        }
    }

    /// A keyframe that nothing ties to the others is left to the general solver, which fixes
    /// its gauge.
    #[test]
    fn an_unanchored_keyframe_goes_to_the_general_solver() {
        let mut w = turning(tight(), 3);
        w.add_keyframe_without_imu(1.0, NavState::at_pose(&Se3::identity()))
            .unwrap();
        let update = w.optimize().unwrap();
        assert_eq!(update.path, "general");
        assert!(update.converged);
    }
}
