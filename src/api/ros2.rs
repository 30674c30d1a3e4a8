//! A session's ROS 2 binding, as given in its creation request (`"ros2": {…}`): which topics of
//! robots that speak rmw_zenoh feed it, how odometry becomes keyframes, and where the optimised
//! trajectory goes. The transport layer (`transport::ros2`) runs it; this is only its wire form
//! and validation.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::ServiceError;
use crate::geometry::preintegration::ImuNoise;

/// The ROS 2 topics a session reads and writes over rmw_zenoh. Topic names are ROS names
/// (`/odom`, `robot1/odom`); an empty or absent output topic is not published.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Ros2Binding {
    /// `ROS_DOMAIN_ID` of the robots (the first component of every key expression).
    #[serde(default)]
    pub domain_id: u32,
    /// The node factord appears as in `ros2 node list`; `factord_<session>` when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub node_name: Option<String>,
    /// `nav_msgs/msg/Odometry`: keyframes and the relative poses between them.
    pub odometry_topic: String,
    /// `sensor_msgs/msg/Imu`: the samples a `sliding_window` session pre-integrates between
    /// keyframes (required there; a pose graph has no use for them).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub imu_topic: Option<String>,
    /// `sliding_window` sessions: the keyframes the window keeps (its `start` message's).
    #[serde(default = "default_window")]
    pub window: usize,
    /// `sliding_window` sessions: the IMU's noise; default EuRoC's (ADIS16448).
    #[serde(default = "default_imu_noise")]
    #[schema(schema_with = super::fusion::imu_noise_schema)]
    pub imu_noise: ImuNoise,
    /// `geometry_msgs/msg/PoseWithCovarianceStamped`: absolute priors (GNSS, map matching) on
    /// the keyframe nearest in time.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub prior_topic: Option<String>,
    /// `factord_msgs/msg/LoopClosure` (`clients/ros2/factord_msgs`): relative poses between
    /// the keyframes nearest two stamps (`pose_graph_3d` only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub loop_closure_topic: Option<String>,
    /// `factord_msgs/msg/LandmarkSighting`: landmark positions in the body frame of the
    /// keyframe nearest their stamp (`pose_graph_3d` only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub landmark_topic: Option<String>,
    /// Seconds a loop closure's or a landmark sighting's stamp may be from the keyframe it
    /// attaches to (0 to 10); farther, the message is refused.
    #[serde(default = "default_keyframe_tolerance")]
    pub keyframe_tolerance: f64,
    /// `nav_msgs/msg/Path`: the optimised keyframe trajectory after each solve.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub path_topic: Option<String>,
    /// `geometry_msgs/msg/PoseWithCovarianceStamped`: the newest keyframe's optimised pose and
    /// marginal covariance after each solve.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pose_topic: Option<String>,
    /// `std_srvs/srv/Trigger` services `<namespace>/optimize`, `<namespace>/export` (the
    /// trajectory as TUM text) and `<namespace>/reset` (the session emptied, bound again).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub service_namespace: Option<String>,
    /// `visualization_msgs/msg/MarkerArray`: the graph after each solve (keyframes, odometry
    /// edges, loop closures coloured by χ², landmarks), latched, for rviz and Foxglove.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub markers_topic: Option<String>,
    /// `tf2_msgs/msg/TFMessage`: the `map → odom` correction (from `map_frame` to odometry's
    /// `header.frame_id`), as a localisation node publishes it; usually `/tf`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tf_topic: Option<String>,
    /// Seconds the correction is dated after the newest odometry stamp, so that lookups at the
    /// robot's newest time find it (AMCL's `transform_tolerance`); 0 to 10.
    #[serde(default = "default_transform_tolerance")]
    pub transform_tolerance: f64,
    /// `header.frame_id` of what is published (the frame the trajectory is optimised in).
    #[serde(default = "default_map_frame")]
    pub map_frame: String,
    /// A session with `robots`: the odometry frame of each robot merged into the map, the
    /// child of its `map_frame → …` transform on `tf_topic`; `{robot}` stands for the robot's
    /// id (its key character, `a`, or `x` and its hex code for one that is no letter or digit).
    #[serde(default = "default_robot_odom_frame")]
    pub robot_odom_frame: String,
    /// A session with `robots`: one node per robot, `{"<robot id>": "<namespace>"}` (e.g.
    /// `{"a": "/husky1", "b": "/husky2"}`). Each robot's node reads and writes the topics above
    /// in its namespace when they are relative (`odom` is `/husky1/odom`; `/tf` stays `/tf`),
    /// makes that robot's keyframes (keys `robot_key(id, i)`), publishes its path and pose (in
    /// the map once merged, in its own odometry frame until then) and its `map → odom`.
    /// `markers_topic` and `service_namespace` are the session's: the first robot's node
    /// declares them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub robots: Option<BTreeMap<String, String>>,
    /// A session with `robots`: `factord_msgs/msg/RobotLoopClosure`, closures between two
    /// robots (named by namespace or id), taken by the node of the robot they end at.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub robot_loop_closure_topic: Option<String>,
    /// A new keyframe when the robot has moved this far (metres) since the last one…
    #[serde(default = "default_keyframe_distance")]
    pub keyframe_distance: f64,
    /// …or turned this much (radians).
    #[serde(default = "default_keyframe_angle")]
    pub keyframe_angle: f64,
}

fn default_map_frame() -> String {
    "map".into()
}

fn default_robot_odom_frame() -> String {
    "robot_{robot}/odom".into()
}

fn default_window() -> usize {
    10
}

fn default_imu_noise() -> ImuNoise {
    ImuNoise::EUROC
}

fn default_transform_tolerance() -> f64 {
    // slam_toolbox's `transform_timeout`.
    0.2
}

fn default_keyframe_tolerance() -> f64 {
    // Half a 10 Hz odometry period: a stamp of the keyframe's own odometry message matches,
    // one of its neighbours does not.
    0.05
}

fn default_keyframe_distance() -> f64 {
    0.5
}

fn default_keyframe_angle() -> f64 {
    // 15°: typical of lidar/visual keyframing.
    0.2618
}

/// Robot nodes one binding may declare.
pub const MAX_ROBOT_NODES: usize = 64;

/// What stands for the robot's id in [`Ros2Binding::robot_odom_frame`].
const ROBOT: &str = "{robot}";

impl Ros2Binding {
    /// Robot `robot`'s odometry frame id on `/tf` ([`Self::robot_odom_frame`]).
    pub fn robot_odom_frame_of(&self, robot: u8) -> String {
        self.robot_odom_frame
            .replace(ROBOT, &super::robots::robot_id(robot))
    }

    /// The node name, defaulted from the session's.
    pub fn node_name(&self, session: &str) -> String {
        self.node_name
            .clone()
            .unwrap_or_else(|| format!("factord_{}", session.replace('-', "_")))
    }

    /// 400 `invalid_value` at the offending field (`ros2.<field>`).
    pub fn validate(&self) -> Result<(), ServiceError> {
        let invalid = |field: &str, message: String| {
            ServiceError::bad_request("invalid_value", format!("ros2.{field}"), message)
        };
        // rmw_zenoh maps domains onto key expressions; ROS itself allows 0–232.
        if self.domain_id > 232 {
            return Err(invalid("domain_id", "ROS domain ids are 0 to 232".into()));
        }
        self.validate_topics()?;
        if let Some(node) = &self.node_name {
            if node.is_empty() || !node.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
                return Err(invalid(
                    "node_name",
                    format!("`{node}` is not a ROS node name"),
                ));
            }
        }
        self.validate_robots()?;
        if self.map_frame.is_empty() {
            return Err(invalid("map_frame", "a frame id is required".into()));
        }
        let robot_frame = self.robot_odom_frame.replace(ROBOT, "a");
        if !self.robot_odom_frame.contains(ROBOT) || !valid_ros_name(&robot_frame) {
            return Err(invalid(
                "robot_odom_frame",
                format!(
                    "`{}` is not a frame id with `{ROBOT}` in it (one per robot, of \
                     [A-Za-z0-9_/] once `{ROBOT}` is replaced): e.g. `robot_{ROBOT}/odom`",
                    self.robot_odom_frame
                ),
            ));
        }
        for (field, value) in [
            ("keyframe_distance", self.keyframe_distance),
            ("keyframe_angle", self.keyframe_angle),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return Err(invalid(field, format!("{value} is not a finite value ≥ 0")));
            }
        }
        if !(1..=1000).contains(&self.window) {
            return Err(invalid(
                "window",
                format!("{} is not 1 to 1000 keyframes", self.window),
            ));
        }
        let n = &self.imu_noise;
        for (field, value) in [
            ("accel_noise_density", n.accel_noise_density),
            ("gyro_noise_density", n.gyro_noise_density),
            ("accel_random_walk", n.accel_random_walk),
            ("gyro_random_walk", n.gyro_random_walk),
            ("integration_sigma", n.integration_sigma),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return Err(invalid(
                    &format!("imu_noise.{field}"),
                    format!("{value} is not a finite value > 0"),
                ));
            }
        }
        // Beyond seconds, future-dating would hide a correction that stopped being updated.
        if !(0.0..=10.0).contains(&self.transform_tolerance) {
            return Err(invalid(
                "transform_tolerance",
                format!("{} is not in 0 to 10 seconds", self.transform_tolerance),
            ));
        }
        if !(0.0..=10.0).contains(&self.keyframe_tolerance) {
            return Err(invalid(
                "keyframe_tolerance",
                format!("{} is not in 0 to 10 seconds", self.keyframe_tolerance),
            ));
        }
        Ok(())
    }

    /// Every topic a ROS name rmw_zenoh can carry in a key expression.
    fn validate_topics(&self) -> Result<(), ServiceError> {
        let invalid = |field: &str, message: String| {
            ServiceError::bad_request("invalid_value", format!("ros2.{field}"), message)
        };
        let topics = [
            ("odometry_topic", Some(&self.odometry_topic)),
            ("imu_topic", self.imu_topic.as_ref()),
            ("prior_topic", self.prior_topic.as_ref()),
            ("loop_closure_topic", self.loop_closure_topic.as_ref()),
            ("landmark_topic", self.landmark_topic.as_ref()),
            ("path_topic", self.path_topic.as_ref()),
            ("pose_topic", self.pose_topic.as_ref()),
            ("tf_topic", self.tf_topic.as_ref()),
            ("markers_topic", self.markers_topic.as_ref()),
            ("service_namespace", self.service_namespace.as_ref()),
            (
                "robot_loop_closure_topic",
                self.robot_loop_closure_topic.as_ref(),
            ),
        ];
        for (field, topic) in topics {
            if let Some(topic) = topic {
                if !valid_ros_name(topic) {
                    return Err(invalid(
                        field,
                        format!("`{topic}` is not a ROS topic name ([A-Za-z0-9_/], no `//`)"),
                    ));
                }
            }
        }
        Ok(())
    }

    /// `robots`: ids a robot's keys can carry (not `l`, the landmarks'), absolute namespaces,
    /// no two alike; `robot_loop_closure_topic` only with them.
    fn validate_robots(&self) -> Result<(), ServiceError> {
        let invalid = |field: String, message: String| {
            ServiceError::bad_request("invalid_value", format!("ros2.{field}"), message)
        };
        let Some(robots) = &self.robots else {
            return match self.robot_loop_closure_topic {
                Some(_) => Err(invalid(
                    "robot_loop_closure_topic".into(),
                    "closures between robots need `robots` (one node per robot)".into(),
                )),
                None => Ok(()),
            };
        };
        if robots.is_empty() || robots.len() > MAX_ROBOT_NODES {
            return Err(invalid(
                "robots".into(),
                format!("1 to {MAX_ROBOT_NODES} robots, not {}", robots.len()),
            ));
        }
        let mut namespaces = std::collections::HashSet::new();
        for (id, namespace) in robots {
            let field = format!("robots.{id}");
            match super::robots::parse_robot_id(id) {
                Some(b'l') => {
                    return Err(invalid(
                        field,
                        "robot `l` would share its keys with the landmarks".into(),
                    ))
                }
                Some(_) => {}
                None => {
                    return Err(invalid(
                        field,
                        format!(
                            "`{id}` is not a robot id (one letter or digit: its keys' character)"
                        ),
                    ))
                }
            }
            if !(namespace.starts_with('/') && valid_ros_name(namespace)) {
                return Err(invalid(
                    field,
                    format!("`{namespace}` is not an absolute ROS namespace (e.g. `/husky1`)"),
                ));
            }
            if !namespaces.insert(namespace.trim_end_matches('/')) {
                return Err(invalid(
                    field,
                    format!("namespace `{namespace}` is another robot's too"),
                ));
            }
        }
        Ok(())
    }

    /// Whether a session of `kind` can take this binding: odometry makes `se3` keyframes in a
    /// `pose_graph_3d`, or IMU-and-odometry keyframes in a `sliding_window` (which needs the
    /// IMU). 400 `ros2_unsupported_kind` at `ros2`, or `invalid_value` at `ros2.imu_topic`.
    pub fn check_kind(&self, kind: &str) -> Result<(), ServiceError> {
        let imu = |message: &str| {
            ServiceError::bad_request("invalid_value", "ros2.imu_topic", message.to_string())
        };
        // The window builds its own factors from fusion messages: no closures, no landmarks.
        let graph_only = [
            ("loop_closure_topic", &self.loop_closure_topic),
            ("landmark_topic", &self.landmark_topic),
        ];
        for (field, topic) in graph_only {
            if kind != "pose_graph_3d" && topic.is_some() {
                return Err(ServiceError::bad_request(
                    "invalid_value",
                    format!("ros2.{field}"),
                    format!("loop closures and landmarks feed pose_graph_3d sessions, not {kind}"),
                ));
            }
        }
        if self.robots.is_some() && kind != "pose_graph_3d" {
            return Err(ServiceError::bad_request(
                "invalid_value",
                "ros2.robots",
                format!("robots' nodes feed pose_graph_3d sessions, not {kind}"),
            ));
        }
        match (kind, &self.imu_topic) {
            ("pose_graph_3d", None) | ("sliding_window", Some(_)) => Ok(()),
            ("pose_graph_3d", Some(_)) => Err(imu(
                "IMU samples feed sliding_window sessions; a pose_graph_3d takes odometry only",
            )),
            ("sliding_window", None) => Err(imu(
                "a sliding_window session pre-integrates IMU samples between keyframes: \
                 imu_topic is required",
            )),
            _ => Err(ServiceError::bad_request(
                "ros2_unsupported_kind",
                "ros2",
                format!(
                    "a ROS 2 binding needs a pose_graph_3d or sliding_window session, not {kind}"
                ),
            )),
        }
    }
}

/// A ROS topic name as rmw_zenoh can carry it in a key expression: segments of
/// `[A-Za-z0-9_]` separated by single slashes (a leading `/` allowed, no `~` or substitutions).
fn valid_ros_name(name: &str) -> bool {
    let name = name.strip_prefix('/').unwrap_or(name);
    !name.is_empty()
        && name.split('/').all(|segment| {
            !segment.is_empty()
                && segment
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '_')
                && !segment.starts_with(|c: char| c.is_ascii_digit())
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn binding(json: &str) -> Ros2Binding {
        serde_json::from_str(json).expect("a binding")
    }

    #[test]
    fn defaults_fill_what_the_request_leaves_out() {
        let b = binding(r#"{"odometry_topic": "/odom"}"#);
        assert_eq!(b.domain_id, 0);
        assert_eq!(b.map_frame, "map");
        assert_eq!(b.node_name("robot-1"), "factord_robot_1");
        assert!(b.validate().is_ok());
    }

    #[test]
    fn robot_odometry_frames_follow_the_template() {
        let b = binding(r#"{"odometry_topic": "/odom"}"#);
        assert_eq!(b.robot_odom_frame_of(b'b'), "robot_b/odom");
        assert_eq!(b.robot_odom_frame_of(b'*'), "robot_x2a/odom");
        let b = binding(r#"{"odometry_topic": "/odom", "robot_odom_frame": "fleet/{robot}_odom"}"#);
        assert!(b.validate().is_ok());
        assert_eq!(b.robot_odom_frame_of(b'c'), "fleet/c_odom");
        for bad in ["odom", "", "robot_{robot}//odom", "{robot} odom"] {
            let b = Ros2Binding {
                robot_odom_frame: bad.into(),
                ..binding(r#"{"odometry_topic": "/odom"}"#)
            };
            let e = b.validate().expect_err(bad);
            assert_eq!(
                e.body.field.as_deref(),
                Some("ros2.robot_odom_frame"),
                "{bad}"
            );
        }
    }

    #[test]
    fn robot_nodes_need_ids_and_absolute_namespaces_of_their_own() {
        let with = |robots: &str| {
            binding(&format!(
                r#"{{"odometry_topic": "odom", "robots": {robots}}}"#
            ))
        };
        let ok = with(r#"{"a": "/husky1", "b": "/fleet/husky2"}"#);
        assert!(ok.validate().is_ok() && ok.check_kind("pose_graph_3d").is_ok());
        let field = |b: Ros2Binding| b.validate().unwrap_err().body.field.unwrap();
        assert_eq!(field(with(r#"{"l": "/husky1"}"#)), "ros2.robots.l");
        assert_eq!(field(with(r#"{"ab": "/husky1"}"#)), "ros2.robots.ab");
        assert_eq!(field(with(r#"{"a": "husky1"}"#)), "ros2.robots.a");
        assert_eq!(
            field(with(r#"{"a": "/husky1", "b": "/husky1/"}"#)),
            "ros2.robots.b"
        );
        assert_eq!(field(with("{}")), "ros2.robots");
        let closures = binding(r#"{"odometry_topic": "odom", "robot_loop_closure_topic": "/c"}"#);
        assert_eq!(field(closures), "ros2.robot_loop_closure_topic");
        let window = with(r#"{"a": "/husky1"}"#).check_kind("sliding_window");
        assert_eq!(
            window.unwrap_err().body.field.as_deref(),
            Some("ros2.robots")
        );
    }

    #[test]
    fn topic_names_that_cannot_be_key_expressions_are_refused() {
        for bad in ["", "/", "a//b", "odom*", "/1st", "a b"] {
            let b = Ros2Binding {
                odometry_topic: bad.into(),
                ..binding(r#"{"odometry_topic": "/odom"}"#)
            };
            let e = b.validate().expect_err(bad);
            assert_eq!(
                e.body.field.as_deref(),
                Some("ros2.odometry_topic"),
                "{bad}"
            );
        }
        assert!(valid_ros_name("robot1/odom"));
    }

    #[test]
    fn loop_closures_and_landmarks_are_for_pose_graphs_within_a_tolerance() {
        let b = binding(
            r#"{"odometry_topic": "/odom", "loop_closure_topic": "/loops",
                "landmark_topic": "/landmarks", "keyframe_tolerance": 0.1}"#,
        );
        assert!(b.validate().is_ok() && b.check_kind("pose_graph_3d").is_ok());
        let window = Ros2Binding {
            imu_topic: Some("/imu".into()),
            ..b.clone()
        };
        let e = window
            .check_kind("sliding_window")
            .expect_err("no closures");
        assert_eq!(e.body.field.as_deref(), Some("ros2.loop_closure_topic"));
        for tolerance in [-1.0, 10.5, f64::INFINITY] {
            let bad = Ros2Binding {
                keyframe_tolerance: tolerance,
                ..b.clone()
            };
            let e = bad.validate().expect_err("a bad tolerance");
            assert_eq!(e.body.field.as_deref(), Some("ros2.keyframe_tolerance"));
        }
        let bad = Ros2Binding {
            landmark_topic: Some("a//b".into()),
            ..b
        };
        let e = bad.validate().expect_err("a bad topic");
        assert_eq!(e.body.field.as_deref(), Some("ros2.landmark_topic"));
    }

    #[test]
    fn tf_fields_are_checked_at_their_names() {
        let tf = binding(r#"{"odometry_topic": "/odom", "tf_topic": "/tf"}"#);
        assert_eq!(tf.transform_tolerance, 0.2);
        assert!(tf.validate().is_ok());
        let bad_topic = binding(r#"{"odometry_topic": "/odom", "tf_topic": "tf//x"}"#);
        let e = bad_topic.validate().expect_err("a bad tf topic");
        assert_eq!(e.body.field.as_deref(), Some("ros2.tf_topic"));
        for tolerance in [-0.1, 11.0, f64::NAN] {
            let b = Ros2Binding {
                transform_tolerance: tolerance,
                ..tf.clone()
            };
            let e = b.validate().expect_err("a bad tolerance");
            assert_eq!(
                e.body.field.as_deref(),
                Some("ros2.transform_tolerance"),
                "{tolerance}"
            );
        }
    }
}
