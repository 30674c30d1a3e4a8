//! The binding's publications after each solve: the optimised keyframe trajectory as a
//! `nav_msgs/Path` and the newest keyframe as a `geometry_msgs/PoseWithCovarianceStamped`, both
//! in the binding's map frame, stamped with the keyframes' header stamps.
//!
//! The pose's covariance is the keyframe's marginal covariance (`GetMarginals`, one factorisation
//! of the session's Hessian per solve, reused when nothing changed), in factord's tangent space:
//! a body-frame perturbation `(R, t) ⊕ (v, ω) = (R Exp(ω), t + R v)` in the order
//! `[v; ω]`, which is ROS's `[x y z rot_x rot_y rot_z]` order. When it cannot be had (e.g. the
//! keyframe is fixed, or the Hessian is singular) the covariance is all zeros (ROS: unknown).
//!
//! When the binding has a `tf_topic`, each solve also updates the `map → odom` correction
//! (`tf`), and in a session with robots each merged robot's `map → <robot>/odom` (`robot_tf`,
//! also after a merge); with a `markers_topic`, it publishes the graph as markers (`markers`), at most every
//! [`MARKERS_PERIOD`]: they carry the whole graph (megabytes at 100 000 poses), and a robot
//! streaming at 100 Hz would otherwise send one per solve to a display that redraws at a few
//! hertz. A solve inside the period is drawn when it ends, so the last state is always shown.
//!
//! Samples carry rmw_zenoh's attachment (sequence from 1, source time, the publisher's GID).

use std::sync::Arc;
use std::time::Duration;

use tokio::time::Instant;

use nalgebra::Isometry3;
use zenoh::qos::Reliability;
use zenoh_ext::{AdvancedPublisher, AdvancedPublisherBuilderExt, CacheConfig, MissDetectionConfig};

use super::attachment::Attachment;
use super::cdr_codec;
use super::keyframes::from_wire_pose;
use super::markers;
use super::messages::{
    Covariance, Header, Path, Pose, PoseStamped, PoseWithCovariance, PoseWithCovarianceStamped,
    Time,
};
use super::names::Qos;
use super::robot_tf::RobotFrames;
use super::tf::TfBroadcaster;
use crate::api::robots::RobotFrame;
use crate::api::wire::{EstimateQuery, SessionEvent, VariableValue};
use crate::api::{GetGraph, GetMarginals, ListRobots};
use crate::service::{Caller, Command, Recording, Reply, Service};
use crate::session::EventStream;

/// One ROS publisher, declared as rmw_zenoh declares a reliable one: a zenoh-ext advanced
/// publisher, which for a transient-local endpoint also keeps its last samples in a cache,
/// announces itself (publisher detection) and sends sporadic heartbeats (sample-miss
/// detection), so that a late subscriber with history (rmw_zenoh's transient-local
/// subscription) queries the cache and gets them.
pub(super) struct RosPublisher {
    publisher: AdvancedPublisher<'static>,
    gid: [u8; 16],
    sequence: i64,
}

/// Heartbeat period of a transient-local publisher (rmw_zenoh's
/// `SAMPLE_MISS_DETECTION_HEARTBEAT_PERIOD`).
const MISS_DETECTION_HEARTBEAT: Duration = Duration::from_millis(500);

impl RosPublisher {
    pub async fn declare(
        zenoh: &zenoh::Session,
        key: String,
        gid: [u8; 16],
        qos: Qos,
    ) -> zenoh::Result<Self> {
        let mut builder = zenoh
            .declare_publisher(key)
            .reliability(Reliability::Reliable)
            .advanced();
        if let Some(samples) = qos.cached_samples() {
            builder = builder
                .cache(CacheConfig::default().max_samples(samples))
                .publisher_detection()
                .sample_miss_detection(
                    MissDetectionConfig::default().sporadic_heartbeat(MISS_DETECTION_HEARTBEAT),
                );
        }
        Ok(Self {
            publisher: builder.await?,
            gid,
            sequence: 0,
        })
    }

    pub async fn put(&mut self, payload: Vec<u8>) {
        self.sequence += 1;
        let attachment = Attachment::stamped_now(self.sequence, self.gid);
        let put = self
            .publisher
            .put(payload)
            .attachment(attachment.encode().to_vec());
        if let Err(e) = put.await {
            tracing::warn!(
                "ROS publication on {} failed: {e}",
                self.publisher.key_expr()
            );
        }
    }
}

/// The shortest time between two marker publications.
pub(super) const MARKERS_PERIOD: Duration = Duration::from_millis(500);

pub(super) struct Outputs {
    pub service: Arc<Service>,
    pub caller: Arc<Caller>,
    pub session: String,
    pub events: EventStream,
    pub map_frame: String,
    pub path: Option<RosPublisher>,
    pub pose: Option<RosPublisher>,
    pub tf: Option<Arc<TfBroadcaster>>,
    /// A session with robots and a `tf_topic`: each merged robot's `map → odom`.
    pub robot_frames: Option<RobotFrames>,
    pub markers: Option<RosPublisher>,
    /// When markers were last published, and the stamp of a solve not drawn yet.
    pub markers_sent: Option<Instant>,
    pub markers_due: Option<Time>,
    /// A robot's node (`robot_nodes`): the robot whose poses alone it publishes, and the frame
    /// they are in until the robot is merged into the map.
    pub robot: Option<(u8, String)>,
}

impl Outputs {
    /// Publishes after every solve until the session's event stream ends.
    pub async fn run(mut self) {
        loop {
            let event = match self.markers_due_at() {
                Some(at) => tokio::select! {
                    event = self.events.next() => event,
                    () = tokio::time::sleep_until(at) => {
                        self.publish_due_markers().await;
                        continue;
                    }
                },
                None => self.events.next().await,
            };
            let Some(event) = event else { break };
            let mut solved = is_solve(&event) || self.moves_robots(&event);
            // Solves that finished while we published: one publication covers them all.
            while let Some(event) = self.events.try_next() {
                solved |= is_solve(&event) || self.moves_robots(&event);
            }
            if solved {
                self.publish().await;
            }
        }
    }

    /// A merge moves robots' frames: their `/tf` (and a robot's node's path, now in the map)
    /// is published again.
    fn moves_robots(&self, event: &SessionEvent) -> bool {
        (self.robot_frames.is_some() || self.robot.is_some())
            && matches!(event, SessionEvent::Merge { .. })
    }

    /// When the markers of a solve not drawn yet are due.
    fn markers_due_at(&self) -> Option<Instant> {
        self.markers_due?;
        Some(
            self.markers_sent
                .map_or_else(Instant::now, |sent| sent + MARKERS_PERIOD),
        )
    }

    async fn publish(&mut self) {
        let name = self.session.clone();
        let (query, frame_id, in_map) = self.view().await;
        let estimate = Command::get_estimate(name.clone(), query);
        let Ok(Reply::Estimate(estimate)) = self
            .service
            .execute(&self.caller, estimate, Recording::History)
            .await
        else {
            return;
        };
        let mut poses: Vec<PoseStamped> = Vec::with_capacity(estimate.variables.len());
        let mut newest_key = None;
        for v in &estimate.variables {
            if let Some(pose) = pose_stamped(v, &frame_id) {
                poses.push(pose);
                newest_key = Some(v.key);
            }
        }
        if let Some(tf) = &self.tf {
            // A robot not merged yet has no place in the map: no `map → odom` for it.
            if in_map {
                tf.on_solve(&estimate.variables).await;
            }
            if let Some(robots) = &mut self.robot_frames {
                let context = (&*self.service, &*self.caller, name.as_str());
                robots.publish(tf, context, &estimate.variables).await;
            }
        }
        let newest = poses.last().cloned();
        let stamp = newest.as_ref().map(|p| p.header.stamp).unwrap_or_default();
        self.publish_markers(stamp).await;
        if let Some(path) = &mut self.path {
            let message = Path {
                header: Header {
                    stamp: newest.as_ref().map(|p| p.header.stamp).unwrap_or_default(),
                    frame_id,
                },
                poses,
            };
            path.put(cdr_codec::encode(&message)).await;
        }
        let (Some(pose), Some(last), Some(key)) = (&mut self.pose, newest, newest_key) else {
            return;
        };
        let covariance = marginal(&self.service, &self.caller, &name, key).await;
        let message = PoseWithCovarianceStamped {
            header: last.header,
            pose: PoseWithCovariance {
                pose: last.pose,
                covariance,
            },
        };
        pose.put(cdr_codec::encode(&message)).await;
    }

    /// The graph as markers, stamped `stamp` (the newest keyframe's), now or, within
    /// [`MARKERS_PERIOD`] of the last ones, when it ends.
    async fn publish_markers(&mut self, stamp: Time) {
        if self.markers.is_none() {
            return;
        }
        self.markers_due = Some(stamp);
        if self
            .markers_sent
            .is_none_or(|sent| sent.elapsed() >= MARKERS_PERIOD)
        {
            self.publish_due_markers().await;
        }
    }

    async fn publish_due_markers(&mut self) {
        let (Some(publisher), Some(stamp)) = (&mut self.markers, self.markers_due.take()) else {
            return;
        };
        self.markers_sent = Some(Instant::now());
        let command = Command::GetGraph(GetGraph {
            session: self.session.clone(),
        });
        let Ok(Reply::Graph(graph)) = self
            .service
            .execute(&self.caller, command, Recording::History)
            .await
        else {
            return;
        };
        let message = markers::graph_markers(&graph, &self.map_frame, stamp);
        publisher.put(cdr_codec::encode(&message)).await;
    }

    /// What a publication reads, the frame it is in, and whether that is the map: the
    /// session's estimate; for a robot's node its robot's poses, in the map once the robot is
    /// merged into it, in the robot's own odometry frame until then.
    async fn view(&self) -> (EstimateQuery, String, bool) {
        let Some((robot, odom_frame)) = &self.robot else {
            return (EstimateQuery::default(), self.map_frame.clone(), true);
        };
        let command = Command::ListRobots(ListRobots {
            session: self.session.clone(),
        });
        let in_map = match self
            .service
            .execute(&self.caller, command, Recording::History)
            .await
        {
            Ok(Reply::Robots(report)) => report
                .robots
                .iter()
                .any(|r| r.in_map && r.robot.as_bytes() == [*robot]),
            _ => false,
        };
        let (frame, frame_id) = match in_map {
            true => (RobotFrame::Map, self.map_frame.clone()),
            false => (RobotFrame::Odom, odom_frame.clone()),
        };
        let query = EstimateQuery {
            robot: Some((*robot as char).to_string()),
            frame: Some(frame),
            ..EstimateQuery::default()
        };
        (query, frame_id, in_map)
    }
}

/// An `se3` estimate as a stamped pose in `frame_id` (others, and values of the wrong length,
/// skipped).
fn pose_stamped(v: &VariableValue, frame_id: &str) -> Option<PoseStamped> {
    Some(PoseStamped {
        header: Header {
            stamp: v.stamp.map(Time::from_seconds).unwrap_or_default(),
            frame_id: frame_id.to_string(),
        },
        // Renormalised on the way (the wire's shortest round-trip numbers are unit to ~1e-16
        // already; this keeps ROS consumers that check norms strictly happy).
        pose: Pose::from(&se3_estimate(v)?),
    })
}

/// A pose graph's solve, a window's optimisation at a keyframe, or a batch the estimate
/// already reflects: one that adds a pose predicted from consistent odometry changes χ² by
/// nothing, and the session skips its solve (no summary follows), yet the path has a new
/// keyframe.
fn is_solve(event: &SessionEvent) -> bool {
    match event {
        SessionEvent::Summary { .. } | SessionEvent::Window { .. } => true,
        SessionEvent::Ack(ack) => ack.reflected,
        _ => false,
    }
}

/// An `se3` estimate as an isometry (other kinds, and values of the wrong length: `None`).
pub(super) fn se3_estimate(v: &VariableValue) -> Option<Isometry3<f64>> {
    (v.kind == "se3")
        .then(|| from_wire_pose(&v.value))
        .flatten()
}

/// The 6×6 marginal covariance of `key`, row-major; zeros (unknown) when it cannot be had.
async fn marginal(service: &Service, caller: &Caller, session: &str, key: u64) -> Covariance {
    let command = Command::GetMarginals(GetMarginals {
        session: session.into(),
        keys: vec![key],
        joint: false,
    });
    let mut covariance = Covariance::default();
    match service.execute(caller, command, Recording::History).await {
        Ok(Reply::Marginals(marginals)) => {
            let Some(m) = marginals.variables.first() else {
                return covariance;
            };
            // A pose (6×6), or a window's state (15×15) whose first six are the pose's.
            let square = |n| m.covariance.len() == n && m.covariance.iter().all(|r| r.len() == n);
            if square(6) || square(15) {
                for (i, row) in m.covariance.iter().take(6).enumerate() {
                    covariance.0[i * 6..i * 6 + 6].copy_from_slice(&row[..6]);
                }
            }
        }
        Ok(_) => {}
        Err(e) => tracing::debug!(session, "no marginal for the ROS pose: {}", e.body.message),
    }
    covariance
}
