//! One node per robot (`ros2.robots`): a session with robots appears in the ROS graph as one
//! `factord_<session>` node in each robot's namespace, as a multi-robot ROS system namespaces
//! every robot's nodes (`/husky1/odom`, `/husky1/path`).
//!
//! Each robot's node is a binding of its own, run by [`super::run`] with the binding's topics
//! resolved in the robot's namespace ([`node_binding`]): its odometry makes that robot's
//! keyframes (keys `robot_key(id, i)`), its path and pose carry that robot's poses, its `/tf`
//! that robot's `map → odom`. What belongs to the session (markers, the Trigger services) is
//! declared once, by the first robot's node.
//!
//! Closures between robots (`factord_msgs/RobotLoopClosure`) name the robots by namespace or
//! id. Every node subscribes; the node of the robot a closure ends at (`to_robot`, usually the
//! robot that has just recognised the place) takes it, finding the other robot's keyframe in
//! the keyframe stamps all the nodes share ([`SharedKeyframes`]).

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex};

use tokio::sync::watch;

use crate::api::robots::parse_robot_id;
use crate::api::ros2::Ros2Binding;
use crate::variables::Key;

/// Every robot node's keyframe keys by stamp (ns), for closures between robots, and a counter
/// of the keyframes the session has taken: a node holding a closure to another robot's
/// keyframe that is not there yet tries it again when that counter moves.
#[derive(Clone)]
pub(super) struct SharedKeyframes {
    by_robot: Arc<Mutex<HashMap<u8, BTreeMap<i64, Key>>>>,
    taken: Arc<watch::Sender<u64>>,
}

impl Default for SharedKeyframes {
    fn default() -> Self {
        Self {
            by_robot: Arc::default(),
            taken: Arc::new(watch::channel(0).0),
        }
    }
}

impl SharedKeyframes {
    pub fn insert(&self, robot: u8, stamp_ns: i64, key: Key) {
        self.lock().entry(robot).or_default().insert(stamp_ns, key);
    }

    /// Robot `robot`'s keyframe nearest `at` (ns), and its stamp.
    pub fn nearest(&self, robot: u8, at: i64) -> Option<(Key, i64)> {
        super::keyframes::nearest(self.lock().get(&robot)?, at)
    }

    /// The stamp (ns) of robot `robot`'s newest keyframe.
    pub fn newest(&self, robot: u8) -> Option<i64> {
        self.lock().get(&robot)?.keys().next_back().copied()
    }

    /// A node's keyframe batch was taken by the session: closures held for it can enter now.
    pub fn announce_taken(&self) {
        self.taken.send_modify(|n| *n = n.wrapping_add(1));
    }

    /// Told of every [`announce_taken`](Self::announce_taken) from now on.
    pub fn subscribe(&self) -> watch::Receiver<u64> {
        self.taken.subscribe()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<u8, BTreeMap<i64, Key>>> {
        // A panic while inserting leaves a map of stamps, still usable.
        self.by_robot
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }
}

/// Which robot a node serves, and how closures between robots find the others.
#[derive(Clone)]
pub(super) struct RobotNode {
    pub robot: u8,
    pub namespace: String,
    /// The first robot's node also declares the session's own endpoints and refuses closures
    /// that end at no robot of the binding.
    pub first: bool,
    /// Robots by namespace and by id.
    pub names: Arc<HashMap<String, u8>>,
    pub keyframes: SharedKeyframes,
}

impl RobotNode {
    /// The robot a closure names (`a`, `/husky1`, or `husky1/`): as given first, so that an id
    /// is the robot's even where another robot's namespace spells the same (`/a`).
    pub fn robot_named(&self, name: &str) -> Option<u8> {
        let namespace = format!("/{}", name.trim_matches('/'));
        self.names
            .get(name)
            .or_else(|| self.names.get(&namespace))
            .copied()
    }
}

/// The nodes of a binding with `robots`, in the order of their ids; none without.
pub(super) fn nodes(binding: &Ros2Binding) -> Vec<RobotNode> {
    let Some(robots) = &binding.robots else {
        return Vec::new();
    };
    let parsed: Vec<(u8, String)> = robots
        .iter()
        .filter_map(|(id, namespace)| {
            let namespace = namespace.trim_end_matches('/').to_string();
            Some((parse_robot_id(id)?, namespace))
        })
        .collect();
    let mut names = HashMap::new();
    for (robot, namespace) in &parsed {
        names.insert(namespace.clone(), *robot);
        names.insert(crate::api::robots::robot_id(*robot), *robot);
    }
    let (names, keyframes) = (Arc::new(names), SharedKeyframes::default());
    parsed
        .into_iter()
        .enumerate()
        .map(|(i, (robot, namespace))| RobotNode {
            robot,
            namespace,
            first: i == 0,
            names: Arc::clone(&names),
            keyframes: keyframes.clone(),
        })
        .collect()
}

/// A ROS name resolved in `namespace`: absolute names stay, relative ones go under it.
pub(super) fn resolve(namespace: &str, name: &str) -> String {
    match name.starts_with('/') {
        true => name.to_string(),
        false => format!("{}/{name}", namespace.trim_end_matches('/')),
    }
}

/// The binding robot `node`'s node runs: its topics resolved in the robot's namespace, the
/// session's own endpoints on the first node only.
pub(super) fn node_binding(binding: &Ros2Binding, node: &RobotNode) -> Ros2Binding {
    let ns = node.namespace.as_str();
    let in_ns = |topic: &Option<String>| topic.as_deref().map(|t| resolve(ns, t));
    let session_wide = |topic: &Option<String>| match node.first {
        true => topic.as_deref().map(|t| resolve("/", t)),
        false => None,
    };
    Ros2Binding {
        odometry_topic: resolve(ns, &binding.odometry_topic),
        prior_topic: in_ns(&binding.prior_topic),
        loop_closure_topic: in_ns(&binding.loop_closure_topic),
        landmark_topic: in_ns(&binding.landmark_topic),
        path_topic: in_ns(&binding.path_topic),
        pose_topic: in_ns(&binding.pose_topic),
        tf_topic: in_ns(&binding.tf_topic),
        robot_loop_closure_topic: in_ns(&binding.robot_loop_closure_topic),
        markers_topic: session_wide(&binding.markers_topic),
        service_namespace: session_wide(&binding.service_namespace),
        ..binding.clone()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn relative_topics_go_under_each_robots_namespace_and_the_session_once() {
        let binding: Ros2Binding = serde_json::from_value(serde_json::json!({
            "odometry_topic": "odom", "path_topic": "path", "tf_topic": "/tf",
            "markers_topic": "graph", "service_namespace": "/factord",
            "robot_loop_closure_topic": "/closures",
            "robots": {"a": "/husky1/", "b": "/spot"}}))
        .unwrap();
        let nodes = nodes(&binding);
        assert_eq!(nodes.len(), 2);
        let [a, b] = [0, 1].map(|i| node_binding(&binding, &nodes[i]));
        assert_eq!(a.odometry_topic, "/husky1/odom");
        assert_eq!(b.path_topic.as_deref(), Some("/spot/path"));
        assert_eq!(b.tf_topic.as_deref(), Some("/tf"));
        assert_eq!(a.markers_topic.as_deref(), Some("/graph"));
        assert_eq!((b.markers_topic, b.service_namespace), (None, None));
        assert_eq!(b.robot_loop_closure_topic.as_deref(), Some("/closures"));
        let node = &nodes[1];
        assert_eq!(node.robot_named("/husky1"), Some(b'a'));
        assert_eq!(node.robot_named("husky1/"), Some(b'a'));
        assert_eq!(node.robot_named("b"), Some(b'b'));
        assert_eq!(node.robot_named("/c"), None);
        // An id is its robot's, where another robot's namespace spells the same.
        let tricky: Ros2Binding = serde_json::from_value(serde_json::json!({
            "odometry_topic": "odom", "robots": {"a": "/b", "b": "/a"}}))
        .unwrap();
        let node = &super::nodes(&tricky)[0];
        assert_eq!(node.robot_named("a"), Some(b'a'));
        assert_eq!(node.robot_named("/a"), Some(b'b'));
    }

    #[test]
    fn every_node_hears_of_a_keyframe_taken_and_knows_each_robots_newest() {
        let shared = SharedKeyframes::default();
        let (mut a, mut b) = (shared.subscribe(), shared.clone().subscribe());
        assert_eq!(shared.newest(b'a'), None);
        shared.insert(b'a', 20, 7);
        shared.insert(b'a', 10, 6);
        assert_eq!((shared.newest(b'a'), shared.newest(b'b')), (Some(20), None));
        assert!(!a.has_changed().unwrap());
        shared.announce_taken();
        assert!(a.has_changed().unwrap() && b.has_changed().unwrap());
        a.mark_unchanged();
        assert!(!a.has_changed().unwrap() && b.has_changed().unwrap());
        b.mark_unchanged();
    }
}
