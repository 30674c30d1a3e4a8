//! ROS 2 over rmw_zenoh: a session created with a `ros2` binding (`api::ros2::Ros2Binding`)
//! appears in the robots' ROS graph as a node with its subscriptions and publishers, and is fed
//! by their topics with no code of ours on the robot.
//!
//! Everything matches rmw_zenoh_cpp (its `docs/design.md`, `liveliness_utils.cpp`,
//! `attachment_helpers.cpp`), Jazzy's release and later:
//! - samples on `<domain>/<topic>/<dds type>/<RIHS01 hash>` (`names`), CDR payloads with their
//!   encapsulation header (`cdr_codec`), an attachment of sequence, time and GID (`attachment`);
//! - liveliness tokens `@ros2_lv/…` for the node and each endpoint (`names`), held as long as
//!   the session lives, so `ros2 node list` and `ros2 topic list` on the robot see them.
//!
//! In, for a `pose_graph_3d`: `nav_msgs/Odometry` (keyframes, `between_se3`) and
//! `geometry_msgs/PoseWithCovarianceStamped` (`prior_se3`), see `keyframes`; for a
//! `sliding_window`: the same and `sensor_msgs/Imu`, as fusion messages, see `window_feed`.
//! Out after each solve: `nav_msgs/Path` and `geometry_msgs/PoseWithCovarianceStamped`, see
//! `outputs`, the `map → odom` correction on `/tf`, see `tf` (in a session with robots also
//! each merged robot's `map → <robot>/odom`, see `robot_tf`), and the graph as a
//! `visualization_msgs/MarkerArray`, see `markers`. A pose graph also takes loop closures and
//! landmark sightings (`factord_msgs`, `clients/ros2/factord_msgs`), see `closures`; their type
//! hashes are computed from the `.msg` files as rosidl does, see `type_hash`. Messages go through the one
//! command API ([`Service::execute`]) like any client's; nothing here touches a session's
//! state.
//!
//! The binding uses the zenoh adapter's session: robots reach factord through the same router
//! (or peer-to-peer) as any zenoh client. In a fleet (`--fleet`) the binding runs where the
//! session is loaded and follows it: the instance that adopts a moved session binds it, the one
//! that released it leaves the ROS graph (its event stream ended).

mod attachment;
mod bounds;
mod cdr_codec;
mod closures;
mod inputs;
mod keyframes;
mod markers;
mod messages;
mod names;
mod outputs;
mod robot_nodes;
mod robot_tf;
mod services;
mod tf;
mod type_hash;
mod window_feed;

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use zenoh::liveliness::LivelinessToken;

use crate::api::ros2::Ros2Binding;
use crate::service::{Caller, Service};
use crate::session::{EventStream, Session};
use bounds::Stamps;
use inputs::Feeder;
use keyframes::Keyframer;
use messages::{
    RosType, IMU, LANDMARK_SIGHTING, LOOP_CLOSURE, MARKER_ARRAY, ODOMETRY, PATH,
    POSE_WITH_COVARIANCE_STAMPED, ROBOT_LOOP_CLOSURE, TF_MESSAGE,
};
use names::{EndpointKind, NodeName, Qos};
use outputs::RosPublisher;
use robot_nodes::RobotNode;
use tf::TfBroadcaster;
use window_feed::WindowFeed;

/// Node and endpoint ids within our zenoh session, unique as rmw_zenoh's per-context counter.
static NEXT_ENTITY_ID: AtomicU64 = AtomicU64::new(1);

fn next_id() -> u64 {
    NEXT_ENTITY_ID.fetch_add(1, Ordering::Relaxed)
}

#[derive(Debug, thiserror::Error)]
#[error("ROS 2 binding of session {session}: {source}")]
pub struct BindError {
    session: String,
    #[source]
    source: zenoh::Error,
}

/// What a binding runs with: the zenoh adapter's session, the service and who its commands
/// run as, and the largest payload taken (`max_body_bytes`, as for the adapter's own keys).
#[derive(Clone)]
pub struct Context {
    pub zenoh: zenoh::Session,
    pub service: Arc<Service>,
    pub caller: Arc<Caller>,
    pub max_payload: usize,
}

/// Starts `session`'s binding when it has one: one node, or one per robot (`robot_nodes`). It
/// runs while the session lives here: it holds only the session's event stream, which ends
/// when the session is deleted or moves to another fleet instance (whose adoption binds it
/// there).
pub fn bind(context: Context, session: &Arc<Session>) {
    let Some(binding) = session.ros2_binding().cloned() else {
        return;
    };
    let nodes = robot_nodes::nodes(&binding);
    if nodes.is_empty() {
        spawn_node(context, session, (binding.clone(), binding), None);
        return;
    }
    for node in nodes {
        let node_binding = robot_nodes::node_binding(&binding, &node);
        let bindings = (binding.clone(), node_binding);
        spawn_node(context.clone(), session, bindings, Some(node));
    }
}

/// One node: `bindings` are the session's and the node's (for a robot's node, its topics in
/// the robot's namespace; the same otherwise).
fn spawn_node(
    context: Context,
    session: &Arc<Session>,
    bindings: (Ros2Binding, Ros2Binding),
    robot: Option<RobotNode>,
) {
    let (name, events) = (session.name.clone(), session.stream());
    tokio::spawn(async move {
        if let Err(e) = run(context, (name, events), bindings, robot).await {
            tracing::error!("{e}");
        }
    });
}

async fn run(
    context: Context,
    (session, events): (String, EventStream),
    // The session's binding, and this node's (its topics in the robot's namespace).
    (session_binding, binding): (Ros2Binding, Ros2Binding),
    robot: Option<RobotNode>,
) -> Result<(), BindError> {
    let Context {
        zenoh,
        service,
        caller,
        max_payload,
    } = context;
    let failed = |source| BindError {
        session: session.clone(),
        source,
    };
    let node = NodeName {
        domain_id: binding.domain_id,
        zid: zenoh.zid().to_string(),
        node_id: next_id(),
        namespace: robot.as_ref().map_or("/".into(), |r| r.namespace.clone()),
        name: binding.node_name(&session),
    };
    let mut graph = RosGraph {
        zenoh: &zenoh,
        node: &node,
        domain_id: binding.domain_id,
        tokens: Vec::new(),
    };
    let [odometry, priors, imu, loop_closures, landmarks, robot_loop_closures] =
        graph.subscriptions(&binding).await.map_err(failed)?;
    let odometry = odometry.expect("odometry is always subscribed");
    let [path, pose, tf, markers] = graph.publishers(&binding).await.map_err(failed)?;
    let tf = tf.map(|publisher| tf_broadcaster(publisher, &binding, robot.as_ref()));
    let server = services::Server {
        service: Arc::clone(&service),
        caller: Arc::clone(&caller),
        session: session.clone(),
        // A reset creates the session again with its whole binding, every robot's node.
        binding: session_binding,
    };
    let servers = graph.services(&binding, server).await.map_err(failed)?;
    // The node joins the ROS graph last: zenoh delivers a session's declarations in order, so a
    // robot that sees the node also knows its subscriptions, and its first message is heard
    // (declared first, a put right after the node appeared could reach no subscriber yet).
    graph.hold(node.node_token()).await.map_err(failed)?;
    tracing::info!(
        session,
        "ROS 2 binding: node {} on domain {}",
        node.name,
        binding.domain_id
    );
    let (feeder, stamps) =
        resumed_feeder(&service, &caller, &session, &binding, robot.as_ref()).await;
    let inputs = inputs::Inputs {
        service: Arc::clone(&service),
        caller: Arc::clone(&caller),
        session: session.clone(),
        feeder,
        odometry,
        priors,
        imu,
        loop_closures,
        landmarks,
        robot_loop_closures,
        robot: robot.clone(),
        tf: tf.clone(),
        refused: Arc::default(),
        max_payload,
        stamps,
        ahead: Vec::new(),
        keyframes_taken: robot.as_ref().map(|node| node.keyframes.subscribe()),
    };
    let inputs = tokio::spawn(inputs.run());
    let outputs = outputs::Outputs {
        robot_frames: robot_frames(&service, &session, &binding, tf.is_some(), robot.as_ref()),
        robot: robot.map(|node| (node.robot, binding.robot_odom_frame_of(node.robot))),
        service,
        caller,
        session,
        events,
        map_frame: binding.map_frame.clone(),
        path,
        pose,
        tf,
        markers,
        markers_sent: None,
        markers_due: None,
    };
    outputs.run().await;
    // The session is gone from here: leave the ROS graph.
    inputs.abort();
    for server in servers {
        server.abort();
    }
    drop(graph.tokens);
    Ok(())
}

/// `map → odom` on `/tf`: a robot's node names its child frame by the robot (its
/// `robot_odom_frame`), the one node of a binding without robots by what odometry says.
fn tf_broadcaster(
    publisher: RosPublisher,
    binding: &Ros2Binding,
    robot: Option<&RobotNode>,
) -> Arc<TfBroadcaster> {
    let tf = TfBroadcaster::new(
        publisher,
        binding.map_frame.clone(),
        binding.transform_tolerance,
    );
    Arc::new(match robot {
        Some(node) => tf.with_odom_frame(binding.robot_odom_frame_of(node.robot)),
        None => tf,
    })
}

/// Each merged robot's `map → odom` on `/tf`, for a session with robots whose binding has a
/// `tf_topic`. A session's robots are set at its creation: they are there now or never. A
/// robot's node publishes only its own robot's, as its `tf_broadcaster`'s correction.
fn robot_frames(
    service: &Service,
    session: &str,
    binding: &Ros2Binding,
    has_tf: bool,
    robot: Option<&RobotNode>,
) -> Option<robot_tf::RobotFrames> {
    if robot.is_some() {
        return None;
    }
    let has_robots = service
        .session(session)
        .is_ok_and(|s| s.robots_options().is_some());
    (has_tf && has_robots).then(|| robot_tf::RobotFrames::new(binding))
}

/// The binding's node in the robots' ROS graph while it declares its endpoints: each endpoint
/// is a zenoh key and a liveliness token, held (`tokens`) as long as the binding lives.
struct RosGraph<'a> {
    zenoh: &'a zenoh::Session,
    node: &'a NodeName,
    domain_id: u32,
    tokens: Vec<LivelinessToken>,
}

type Subscription =
    zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>;

impl RosGraph<'_> {
    /// An endpoint's liveliness token (to hold) and its key.
    fn endpoint(
        &self,
        kind: EndpointKind,
        topic: &str,
        ros_type: &RosType,
        qos: Qos,
    ) -> (String, String) {
        let token = self
            .node
            .endpoint_token(next_id(), kind, topic, ros_type, qos);
        (token, names::topic_key(self.domain_id, topic, ros_type))
    }

    async fn hold(&mut self, token: String) -> zenoh::Result<()> {
        self.tokens.push(declare_token(self.zenoh, token).await?);
        Ok(())
    }

    /// Odometry, priors, IMU, loop closures, landmark sightings and closures between robots:
    /// odometry always, the others when the binding names their topics.
    async fn subscriptions(
        &mut self,
        binding: &Ros2Binding,
    ) -> zenoh::Result<[Option<Subscription>; 6]> {
        let wanted = [
            (Some(&binding.odometry_topic), &ODOMETRY),
            (binding.prior_topic.as_ref(), &POSE_WITH_COVARIANCE_STAMPED),
            (binding.imu_topic.as_ref(), &IMU),
            (binding.loop_closure_topic.as_ref(), &*LOOP_CLOSURE),
            (binding.landmark_topic.as_ref(), &*LANDMARK_SIGHTING),
            (
                binding.robot_loop_closure_topic.as_ref(),
                &*ROBOT_LOOP_CLOSURE,
            ),
        ];
        let mut subscriptions: [Option<Subscription>; 6] = Default::default();
        for (slot, (topic, ros_type)) in subscriptions.iter_mut().zip(wanted) {
            let Some(topic) = topic else { continue };
            let (token, key) =
                self.endpoint(EndpointKind::Subscription, topic, ros_type, Qos::Default);
            *slot = Some(self.zenoh.declare_subscriber(&key).await?);
            self.hold(token).await?;
        }
        Ok(subscriptions)
    }

    /// Path, pose, `/tf` and markers, when the binding names their topics. The path and the
    /// markers are latched (transient local): an operator's rviz started after the robot gets
    /// the last trajectory and graph at once.
    async fn publishers(
        &mut self,
        binding: &Ros2Binding,
    ) -> zenoh::Result<[Option<RosPublisher>; 4]> {
        let wanted = [
            (binding.path_topic.as_ref(), &PATH, Qos::Latched),
            (
                binding.pose_topic.as_ref(),
                &POSE_WITH_COVARIANCE_STAMPED,
                Qos::Default,
            ),
            (binding.tf_topic.as_ref(), &TF_MESSAGE, Qos::Default),
            (binding.markers_topic.as_ref(), &MARKER_ARRAY, Qos::Latched),
        ];
        let mut publishers: [Option<RosPublisher>; 4] = Default::default();
        for (slot, (topic, ros_type, qos)) in publishers.iter_mut().zip(wanted) {
            let Some(topic) = topic else { continue };
            let (token, key) = self.endpoint(EndpointKind::Publisher, topic, ros_type, qos);
            let gid = names::gid_of(&token);
            *slot = Some(RosPublisher::declare(self.zenoh, key, gid, qos).await?);
            self.hold(token).await?;
        }
        Ok(publishers)
    }

    /// The `service_namespace`'s Trigger services: a queryable each, answered in a task each.
    async fn services(
        &mut self,
        binding: &Ros2Binding,
        server: services::Server,
    ) -> zenoh::Result<Vec<tokio::task::JoinHandle<()>>> {
        let mut servers = Vec::new();
        let Some(namespace) = &binding.service_namespace else {
            return Ok(servers);
        };
        for action in services::Action::ALL {
            let name = format!("{}/{}", namespace.trim_end_matches('/'), action.name());
            let (token, key) = self.endpoint(
                EndpointKind::Service,
                &name,
                &services::TRIGGER,
                Qos::Default,
            );
            let queryable = self.zenoh.declare_queryable(&key).complete(true).await?;
            self.hold(token).await?;
            let server = server.clone();
            servers.push(tokio::spawn(async move {
                while let Ok(query) = queryable.recv_async().await {
                    server.answer(action, query).await;
                }
            }));
        }
        Ok(servers)
    }
}

/// The binding's feeder (a window's for an IMU topic, see `Ros2Binding::check_kind`, else a
/// keyframer) and its stamps, resumed after what the session already holds (a restart).
async fn resumed_feeder(
    service: &Arc<Service>,
    caller: &Arc<Caller>,
    session: &str,
    binding: &Ros2Binding,
    robot: Option<&RobotNode>,
) -> (Feeder, Stamps) {
    let mut feeder = match (&binding.imu_topic, robot) {
        (Some(_), _) => Feeder::Window(Box::new(WindowFeed::new(binding))),
        (None, Some(node)) => Feeder::Graph(Keyframer::for_robot(
            binding,
            node.robot,
            node.keyframes.clone(),
        )),
        (None, None) => Feeder::Graph(Keyframer::new(binding)),
    };
    let mut stamps = Stamps::default();
    let robot = robot.map(|node| node.robot);
    if let Some(existing) = existing_keyframes(service, caller, session, robot).await {
        let newest = existing.keyframes.iter().map(|&(_, t)| t).reduce(f64::max);
        match &mut feeder {
            Feeder::Window(feed) => feed.resume_after(existing.max_key),
            Feeder::Graph(keyframer) => {
                keyframer.resume_after(existing.max_key, existing.keyframes);
                keyframer.resume_landmarks(existing.landmarks);
            }
        }
        if let Some(t) = newest {
            stamps.resume_after(t);
        }
    }
    (feeder, stamps)
}

/// What a session that already has variables (recovered after a restart) holds, of one robot's
/// keyframes for a robot's node.
struct Existing {
    /// The highest keyframe key (landmark keys, `('l' << 56) | id`, apart).
    max_key: u64,
    /// The keyframes with a stamp.
    keyframes: Vec<(u64, f64)>,
    landmarks: Vec<u64>,
}

async fn existing_keyframes(
    service: &Service,
    caller: &Caller,
    session: &str,
    robot: Option<u8>,
) -> Option<Existing> {
    let query = crate::api::wire::EstimateQuery::default();
    let command = crate::service::Command::get_estimate(session.into(), query);
    match service
        .execute(caller, command, crate::service::Recording::History)
        .await
    {
        Ok(crate::service::Reply::Estimate(estimate)) => {
            let (landmarks, mut keyframes): (Vec<_>, Vec<_>) = estimate
                .variables
                .iter()
                .partition(|v| closures::is_landmark(v.key));
            if let Some(robot) = robot {
                keyframes.retain(|v| v.key >> 56 == u64::from(robot));
            }
            Some(Existing {
                max_key: keyframes.iter().map(|v| v.key).max()?,
                keyframes: keyframes
                    .iter()
                    .filter_map(|v| Some((v.key, v.stamp?)))
                    .collect(),
                landmarks: landmarks.iter().map(|v| v.key).collect(),
            })
        }
        _ => None,
    }
}

async fn declare_token(zenoh: &zenoh::Session, key: String) -> zenoh::Result<LivelinessToken> {
    zenoh.liveliness().declare_token(key).await
}
