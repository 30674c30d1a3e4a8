//! Each robot's own view of a session with robots, on keys of its own, so a robot subscribes
//! only to what it needs (`<id>` is [`robot_id`]: the robot's character, `a`):
//! - `<p>/<s>/robot/<id>/poses` and `…/odom_poses`: the robot's estimates (its keys only), in
//!   the map frame and in its own odometry frame, as `out/poses` carries the session's (the
//!   same JSON estimate event); `…/bin/poses` and `…/bin/odom_poses` in binary, as `bin/poses`
//!   (`crate::api::poses_binary`). A `lagged` marker goes on all four, in JSON.
//! - `<p>/<s>/robot/<id>/map_from_odom`: where the robot's odometry frame sits in the map
//!   ([`RobotFrameReport`]: `map_from_odom`, `in_map`, its component), published when it
//!   changes (a merge) and when the robot first appears.
//!
//! The estimates are the session's estimate events split by robot (after coalescing, as on
//! `out/poses`): a delta, the robot's variables that changed. In the odometry frame they are
//! moved by the robot's frame *as of the estimate's sequence* (`Session::odometry_frames_at`),
//! so an estimate computed before a merge is not moved by the merge's transform.
//!
//! As on the session's keys, nothing is serialised for a key no subscriber would receive
//! (zenoh's matching status, [`Heard`]); a robot's publishers are declared when its first pose
//! appears in an estimate. Unlike the session's, a robot's stream starts whole: when zenoh
//! tells the server that a key has an audience again (nobody heard it before), the robot's
//! whole trajectory is put on it at once, read from the session then, and the deltas follow;
//! `map_from_odom` is put again too. A robot that connects late, or whose keys the server
//! declared a moment before zenoh (through a router) matched them, needs no query first and
//! no later solve. A second subscriber joining one that stays gets the deltas only (zenoh's
//! status says "heard", not by whom): it queries first. The queryables
//! (`robot/<id>/estimate`, `robot/<id>/map_from_odom`) are in `robot_queries`.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::{Arc, Weak};
use std::time::Instant;

use tokio::sync::Notify;
use zenoh::bytes::Encoding;
use zenoh::qos::CongestionControl;
use zenoh::Wait;

use super::forward::put_event;
use super::heard::Heard;
use crate::api::poses_binary;
use crate::api::robots::{robot_id, robot_key, robot_of_key, RobotFrameReport, RobotReport};
use crate::api::wire::{Estimate, EstimateQuery, SessionEvent};
use crate::session::Session;

/// The robot streams of one session with robots.
pub(super) struct RobotStreams {
    prefix: String,
    name: String,
    session: Weak<Session>,
    robots: BTreeMap<u8, RobotKeys>,
    /// Characters of keys seen in estimates that name no robot of the session (yet).
    not_robots: BTreeSet<u8>,
    /// What each robot's `map_from_odom` key last carried, and to which audience (the key's
    /// [`Heard::matched`] then).
    announced: BTreeMap<u8, (RobotReport, u64)>,
    /// Woken when one of the robots' keys becomes heard.
    audience: Arc<Notify>,
}

/// One robot's publication keys.
struct RobotKeys {
    poses: Vec<PoseStream>,
    frame: Heard,
    frame_key: String,
}

struct PoseStream {
    key: String,
    odometry_frame: bool,
    binary: bool,
    heard: Heard,
    /// `heard` and its audience as one publication read them: the decision to put on the key
    /// and what `served` records use the same reading, so an audience zenoh reports in the
    /// middle of a publication is served whole by the next one.
    live: Option<u64>,
    /// The audience ([`Heard::matched`]) that got the robot's whole trajectory already, so a
    /// new one gets the whole trajectory, not only what changed since.
    served: Option<u64>,
}

impl RobotStreams {
    /// The streams of `session` when it holds robots.
    pub(super) fn of(session: &Arc<Session>, prefix: &str) -> Option<Self> {
        session.robots_options()?;
        Some(Self {
            prefix: prefix.to_string(),
            name: session.name.clone(),
            session: Arc::downgrade(session),
            robots: BTreeMap::new(),
            not_robots: BTreeSet::new(),
            announced: BTreeMap::new(),
            audience: Arc::new(Notify::new()),
        })
    }

    /// Notified when one of the robots' keys gets an audience it did not have: then
    /// [`Self::serve_new_audiences`] has something to put.
    pub(super) fn audience(&self) -> Arc<Notify> {
        Arc::clone(&self.audience)
    }

    /// Puts the whole trajectory on each robot pose key whose audience has not got it, and
    /// `map_from_odom` on each frame key whose audience has not got the current one; what an
    /// audience that arrives while no estimate is published would otherwise wait for.
    pub(super) fn serve_new_audiences(&mut self, zenoh: &zenoh::Session) {
        self.read_audiences();
        let (puts, poses) = self.put_by_robot(zenoh, BTreeMap::new());
        self.announce_frames(zenoh);
        tracing::debug!(
            session = self.name,
            puts,
            poses,
            "robot streams served a new audience"
        );
    }

    /// Declares the keys of the robots whose poses appear in `run` for the first time.
    pub(super) async fn discover(&mut self, zenoh: &zenoh::Session, run: &[Arc<SessionEvent>]) {
        let mut seen = BTreeSet::new();
        for event in run {
            if let SessionEvent::Estimate(estimate) = &**event {
                seen.extend(
                    estimate
                        .variables
                        .iter()
                        .filter(|v| matches!(&*v.kind, "se2" | "se3"))
                        .filter_map(|v| robot_of_key(v.key))
                        .map(|c| c as u8)
                        .filter(|c| !self.robots.contains_key(c) && !self.not_robots.contains(c)),
                );
            }
        }
        if seen.is_empty() {
            return;
        }
        let Some(session) = self.session.upgrade() else {
            return;
        };
        let robots: BTreeSet<u8> = session
            .robot_reports()
            .unwrap_or_default()
            .iter()
            .filter_map(|r| r.robot.bytes().next())
            .collect();
        for robot in seen {
            if !robots.contains(&robot) {
                self.not_robots.insert(robot);
                continue;
            }
            let keys =
                RobotKeys::declare(zenoh, &self.prefix, &self.name, robot, &self.audience).await;
            self.robots.insert(robot, keys);
        }
    }

    /// Whether some subscriber would receive something of `event` on a robot's key.
    pub(super) fn hears(&self, event: &SessionEvent) -> bool {
        match event {
            SessionEvent::Estimate(_) | SessionEvent::Lagged { .. } => self
                .robots
                .values()
                .any(|r| r.poses.iter().any(|p| p.heard.now()) || r.frame.now()),
            SessionEvent::Merge { .. } => self.robots.values().any(|r| r.frame.now()),
            _ => false,
        }
    }

    /// Puts what of `run` (coalesced) goes on the robots' keys.
    pub(super) fn publish(&mut self, zenoh: &zenoh::Session, run: &[Arc<SessionEvent>]) {
        let started = Instant::now();
        let (mut puts, mut poses) = (0, 0);
        let mut frames_may_have_moved = false;
        for event in run {
            match &**event {
                SessionEvent::Estimate(estimate) => {
                    let (p, v) = self.publish_estimate(zenoh, estimate);
                    (puts, poses) = (puts + p, poses + v);
                    frames_may_have_moved = true;
                }
                SessionEvent::Lagged { .. } => {
                    let body = serde_json::to_vec(&**event).expect("events serialise");
                    let heard = self.robots.values().flat_map(|r| &r.poses);
                    for stream in heard.filter(|p| p.heard.now()) {
                        let put = put_event(
                            zenoh,
                            &stream.key,
                            body.clone(),
                            Encoding::APPLICATION_JSON,
                            event,
                        );
                        self.report(put.wait(), &stream.key);
                    }
                }
                SessionEvent::Merge { .. } => frames_may_have_moved = true,
                _ => {}
            }
        }
        if frames_may_have_moved {
            self.announce_frames(zenoh);
        }
        if puts > 0 {
            // What benches/history/issue-54-robots.md measures: the cost per solve.
            tracing::debug!(
                session = self.name,
                puts,
                poses,
                micros = started.elapsed().as_micros() as u64,
                "robot streams published"
            );
        }
    }

    /// `estimate` split by robot, put on each robot's pose keys that some subscriber hears;
    /// a robot with a subscriber not served yet gets its whole trajectory instead. Returns
    /// how many puts carried how many poses in all.
    fn publish_estimate(&mut self, zenoh: &zenoh::Session, estimate: &Estimate) -> (usize, usize) {
        self.read_audiences();
        let mut by_robot: BTreeMap<u8, Estimate> = BTreeMap::new();
        for v in &estimate.variables {
            let Some(robot) = robot_of_key(v.key).map(|c| c as u8) else {
                continue;
            };
            if self.robots.get(&robot).is_some_and(RobotKeys::live) {
                by_robot
                    .entry(robot)
                    .or_insert_with(|| Estimate {
                        session: estimate.session.clone(),
                        sequence: estimate.sequence,
                        variables: Vec::new(),
                    })
                    .variables
                    .push(v.clone());
            }
        }
        self.put_by_robot(zenoh, by_robot)
    }

    /// Reads which pose keys are heard, and by which audience, for one publication.
    fn read_audiences(&mut self) {
        for stream in self.robots.values_mut().flat_map(|r| &mut r.poses) {
            // The audience first: a change between the two reads serves the new audience
            // twice, never not at all.
            let audience = stream.heard.matched();
            stream.live = stream.heard.now().then_some(audience);
        }
    }

    /// Puts `by_robot` (each robot's share of an estimate) on the robots' heard pose keys, the
    /// whole trajectory instead where an audience has not had it; returns how many puts
    /// carried how many poses in all.
    fn put_by_robot(
        &mut self,
        zenoh: &zenoh::Session,
        mut by_robot: BTreeMap<u8, Estimate>,
    ) -> (usize, usize) {
        let (mut puts, mut poses) = (0, 0);
        let session = self.session.upgrade();
        for (&robot, keys) in &self.robots {
            let unserved = keys
                .poses
                .iter()
                .any(|p| p.live.is_some() && p.live != p.served);
            if let (true, Some(session)) = (unserved, &session) {
                by_robot.insert(robot, whole_trajectory(session, robot));
            }
        }
        // The frames as of each sequence published (at most two: the event's, a whole read's).
        let mut frames = BTreeMap::new();
        for (robot, in_map) in by_robot {
            let keys = &self.robots[&robot];
            let needs_odometry = keys
                .poses
                .iter()
                .any(|p| p.odometry_frame && p.live.is_some());
            let in_odometry = match (needs_odometry, &session) {
                (true, Some(session)) => {
                    let frames = frames
                        .entry(in_map.sequence)
                        .or_insert_with(|| session.odometry_frames_at(in_map.sequence));
                    let mut moved = in_map.clone();
                    frames.move_into(robot, &mut moved.variables);
                    Some(SessionEvent::Estimate(moved))
                }
                _ => None,
            };
            let in_map = SessionEvent::Estimate(in_map);
            for stream in keys.poses.iter().filter(|p| p.live.is_some()) {
                let carried = match stream.odometry_frame {
                    false => &in_map,
                    true => match &in_odometry {
                        Some(e) => e,
                        None => continue, // the session is gone
                    },
                };
                let (body, encoding) = match (stream.binary, carried) {
                    (true, SessionEvent::Estimate(e)) => {
                        (poses_binary::encode(e), Encoding::APPLICATION_OCTET_STREAM)
                    }
                    _ => (
                        serde_json::to_vec(carried).expect("events serialise"),
                        Encoding::APPLICATION_JSON,
                    ),
                };
                let put = put_event(zenoh, &stream.key, body, encoding, carried);
                self.report(put.wait(), &stream.key);
                puts += 1;
                if let SessionEvent::Estimate(e) = carried {
                    poses += e.variables.len();
                }
            }
        }
        for stream in self.robots.values_mut().flat_map(|r| &mut r.poses) {
            stream.served = stream.live;
        }
        (puts, poses)
    }

    /// Puts each robot's place in the map on its `map_from_odom` key when it differs from
    /// what the key carried last (and someone hears it).
    fn announce_frames(&mut self, zenoh: &zenoh::Session) {
        if !self.robots.values().any(|r| r.frame.now()) {
            return;
        }
        let Some(reports) = self.session.upgrade().and_then(|s| s.robot_reports()) else {
            return;
        };
        for report in reports {
            let Some(robot) = report.robot.bytes().next() else {
                continue;
            };
            let Some(keys) = self.robots.get(&robot).filter(|k| k.frame.now()) else {
                continue;
            };
            let audience = keys.frame.matched();
            let unchanged = self.announced.get(&robot).is_some_and(|(last, heard_by)| {
                *heard_by == audience
                    && last.map_from_odom == report.map_from_odom
                    && last.in_map == report.in_map
                    && last.component == report.component
            });
            if unchanged {
                continue;
            }
            let body = serde_json::to_vec(&RobotFrameReport {
                session: self.name.clone(),
                robot: report.clone(),
            })
            .expect("reports serialise");
            let put = zenoh
                .put(&keys.frame_key, body)
                .encoding(Encoding::APPLICATION_JSON)
                .congestion_control(CongestionControl::Block)
                .express(true)
                .wait();
            self.report(put, &keys.frame_key);
            self.announced.insert(robot, (report, audience));
        }
    }

    fn report(&self, outcome: zenoh::Result<()>, key: &str) {
        if let Err(e) = outcome {
            tracing::warn!(
                "zenoh publication on {key} for session {} failed: {e}",
                self.name
            );
        }
    }
}

/// Robot `robot`'s whole trajectory (its keys' values in the map) now.
fn whole_trajectory(session: &Session, robot: u8) -> Estimate {
    let query = EstimateQuery {
        from: Some(robot_key(robot as char, 0)),
        to: Some(robot_key(robot as char, (1 << 56) - 1)),
        ..EstimateQuery::default()
    };
    session.estimate(&query)
}

impl RobotKeys {
    /// Whether one of its pose keys is heard, as the publication under way read it.
    fn live(&self) -> bool {
        self.poses.iter().any(|p| p.live.is_some())
    }

    async fn declare(
        zenoh: &zenoh::Session,
        prefix: &str,
        session: &str,
        robot: u8,
        audience: &Arc<Notify>,
    ) -> Self {
        let base = robot_key_base(prefix, session, robot);
        let mut poses = Vec::with_capacity(4);
        for (suffix, odometry_frame, binary) in [
            ("poses", false, false),
            ("odom_poses", true, false),
            ("bin/poses", false, true),
            ("bin/odom_poses", true, true),
        ] {
            let key = format!("{base}/{suffix}");
            poses.push(PoseStream {
                heard: Heard::declare(zenoh, key.clone(), Some(Arc::clone(audience))).await,
                key,
                odometry_frame,
                binary,
                live: None,
                served: None,
            });
        }
        let frame_key = format!("{base}/map_from_odom");
        Self {
            poses,
            frame: Heard::declare(zenoh, frame_key.clone(), Some(Arc::clone(audience))).await,
            frame_key,
        }
    }
}

/// `<p>/<s>/robot/<id>`.
fn robot_key_base(prefix: &str, session: &str, robot: u8) -> String {
    format!("{prefix}/{session}/robot/{}", robot_id(robot))
}
