//! The wire messages of `sliding_window` sessions: what a robot sends (`FusionMessage`, in
//! batches) and what it gets back (`FusionAck`, `StateReport`).

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::geometry::preintegration::ImuNoise;
use crate::geometry::NavState;
use crate::variables::Key;
use crate::wire_number;

/// The prior standard deviations of a window's first state (`start.sigmas`): position (m),
/// rotation (rad), velocity (m/s), accelerometer and gyroscope biases.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct InitialSigmas {
    pub position: f64,
    pub rotation: f64,
    pub velocity: f64,
    pub accel_bias: f64,
    pub gyro_bias: f64,
}

impl InitialSigmas {
    /// The first state's prior information: diagonal, 1/σ² over the fifteen tangent
    /// dimensions (position, rotation, velocity, accelerometer and gyroscope biases).
    pub fn information(
        &self,
    ) -> Result<nalgebra::DMatrix<f64>, crate::fusion::window::FusionError> {
        crate::fusion::window::diagonal_information(&[
            (self.position, 3),
            (self.rotation, 3),
            (self.velocity, 3),
            (self.accel_bias, 3),
            (self.gyro_bias, 3),
        ])
    }
}

/// A batch of fusion messages (`POST /v1/sessions/{s}/fusion`, zenoh `…/in/fusion`).
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct FusionBatch {
    #[serde(deserialize_with = "super::wire_list::items")]
    pub messages: Vec<FusionMessage>,
}

fn default_window() -> usize {
    10
}
fn default_gravity() -> f64 {
    9.81
}
fn default_noise() -> ImuNoise {
    ImuNoise::EUROC
}

/// `InitialSigmas`' schema (that type lives below the api layer, without a schema of its own).
fn initial_sigmas_schema() -> utoipa::openapi::schema::Object {
    numbers_object(
        &[
            "position",
            "rotation",
            "velocity",
            "accel_bias",
            "gyro_bias",
        ],
        &[],
    )
}

/// `ImuNoise`'s schema (see [`initial_sigmas_schema`]).
pub(super) fn imu_noise_schema() -> utoipa::openapi::schema::Object {
    numbers_object(
        &[
            "accel_noise_density",
            "gyro_noise_density",
            "accel_random_walk",
            "gyro_random_walk",
        ],
        &["integration_sigma"],
    )
}

/// A closed object of number fields, `required` then `optional` ones.
fn numbers_object(required: &[&str], optional: &[&str]) -> utoipa::openapi::schema::Object {
    use utoipa::openapi::schema::{AdditionalProperties, ObjectBuilder, Type};
    let number = || ObjectBuilder::new().schema_type(Type::Number);
    let mut object = ObjectBuilder::new()
        .schema_type(Type::Object)
        .additional_properties(Some(AdditionalProperties::FreeForm(false)));
    for name in required {
        object = object.property(*name, number()).required(*name);
    }
    for name in optional {
        object = object.property(*name, number());
    }
    object.build()
}

#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum FusionMessage {
    /// The first keyframe (key 0) and the window's parameters; once per session.
    Start(Box<StartMessage>),
    /// One IMU sample: accelerometer m/s², gyroscope rad/s, body frame.
    Imu {
        t: f64,
        accel: [f64; 3],
        gyro: [f64; 3],
    },
    /// A keyframe at `t` from the samples since the previous one; the window is then optimised.
    Keyframe { t: f64 },
    /// A keyframe at `t` from a measurement pre-integrated on the robot since the previous
    /// keyframe (GTSAM's manifold pre-integration: matrices row-major, the covariance 15×15 in
    /// the order rotation, position, velocity, accelerometer bias, gyroscope bias).
    PreintegratedKeyframe(Box<PreintegratedKeyframeMessage>),
    /// Lidar odometry: the pose of `to` in the frame of `from`.
    RelativePose {
        #[serde(deserialize_with = "wire_number::u64")]
        from: Key,
        #[serde(deserialize_with = "wire_number::u64")]
        to: Key,
        position: [f64; 3],
        rotation_xyzw: [f64; 4],
        sigma_position: f64,
        sigma_rotation: f64,
    },
    /// Map matching: the world pose of `key`.
    PosePrior {
        #[serde(deserialize_with = "wire_number::u64")]
        key: Key,
        position: [f64; 3],
        rotation_xyzw: [f64; 4],
        sigma_position: f64,
        sigma_rotation: f64,
    },
    /// GNSS: the world position of `key`.
    PositionPrior {
        #[serde(deserialize_with = "wire_number::u64")]
        key: Key,
        position: [f64; 3],
        sigma: f64,
    },
}

/// The fields of [`FusionMessage::Start`] (boxed: the largest messages stay out of every
/// element of a batch's message list).
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct StartMessage {
    pub t: f64,
    pub position: [f64; 3],
    pub rotation_xyzw: [f64; 4],
    #[serde(default)]
    pub velocity: [f64; 3],
    #[serde(default)]
    pub accel_bias: [f64; 3],
    #[serde(default)]
    pub gyro_bias: [f64; 3],
    #[schema(schema_with = initial_sigmas_schema)]
    pub sigmas: InitialSigmas,
    #[serde(default = "default_window", deserialize_with = "wire_number::usize")]
    pub window: usize,
    #[serde(default = "default_gravity")]
    pub gravity: f64,
    #[serde(default = "default_noise")]
    #[schema(schema_with = imu_noise_schema)]
    pub imu_noise: ImuNoise,
}

/// The fields of [`FusionMessage::PreintegratedKeyframe`] (boxed, as [`StartMessage`]).
#[derive(Clone, Debug, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PreintegratedKeyframeMessage {
    pub t: f64,
    pub delta_t: f64,
    pub delta_rotation_xyzw: [f64; 4],
    pub delta_velocity: [f64; 3],
    pub delta_position: [f64; 3],
    /// The bias the samples were corrected with.
    pub accel_bias: [f64; 3],
    pub gyro_bias: [f64; 3],
    pub d_rotation_d_gyro_bias: [f64; 9],
    pub d_velocity_d_accel_bias: [f64; 9],
    pub d_velocity_d_gyro_bias: [f64; 9],
    pub d_position_d_accel_bias: [f64; 9],
    pub d_position_d_gyro_bias: [f64; 9],
    pub covariance: Vec<f64>,
}

/// One keyframe's state on the wire.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
pub struct StateReport {
    pub key: Key,
    pub t: f64,
    pub position: [f64; 3],
    pub rotation_xyzw: [f64; 4],
    pub velocity: [f64; 3],
    pub accel_bias: [f64; 3],
    pub gyro_bias: [f64; 3],
}

impl StateReport {
    pub fn new(key: Key, t: f64, s: &NavState) -> Self {
        let q = s.rotation.quaternion();
        let a = |v: &Vector3<f64>| [v.x, v.y, v.z];
        Self {
            key,
            t,
            position: a(&s.position),
            rotation_xyzw: [q.i, q.j, q.k, q.w],
            velocity: a(&s.velocity),
            accel_bias: a(&s.accel_bias),
            gyro_bias: a(&s.gyro_bias),
        }
    }
}

/// What a fusion batch did.
#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct FusionAck {
    pub session: String,
    pub applied: usize,
    /// Keys of the keyframes the batch created, in order.
    pub keyframes: Vec<Key>,
    /// The newest state after the batch (after its last keyframe's optimisation).
    #[schema(required = true)]
    pub latest: Option<StateReport>,
}
