//! Several robots in one session, each in its own odometry frame until closures merge them.
//!
//! A robot is named by its pose keys (`(c << 56) | i`, GTSAM's `Symbol`, see
//! [`crate::api::robots`]); its values arrive in its own odometry frame and nothing says where
//! that frame sits in the map. So each robot's poses found a *component* of their own, solved
//! on its own (the solver's gauge anchors every component at its lowest key, the robot's first
//! pose, where the robot put it), and the map is the component of the robot seen first.
//!
//! A factor that joins two components that both hold robots (an inter-robot closure, or a
//! landmark one robot placed seen by another) is *held*: accepted, acknowledged and journalled,
//! but kept out of the problem, because its error in two unrelated frames is meaningless and one
//! wrong closure would fold one robot's map onto another's. When `min_closures` held closures
//! between the same two components agree with each other (`consensus`), the newer component
//! *merges* into the older: every value of it moves by the transform the consensus implies
//! (`frame`), the agreeing closures enter the problem, and the moved robots' frames record where
//! their odometry now sits, so their later values (still in their odometry frames) are moved on
//! arrival too. The closures that disagreed stay held, within one component now (`rejected` in
//! the report), and enter once they fit the map (checked every few batches).
//!
//! Decisions are made once, when a batch is accepted, from the estimate then; the journal
//! records each merge (or admission) after its batch, and a replay applies the record instead
//! of deciding again.
//! Holding and routing depend only on the keys and the merges so far, so they replay the same.

mod apply;
mod consensus;
mod plan;
mod session;

use std::collections::{BTreeMap, BTreeSet, HashMap};

pub(crate) use crate::variables::frame::Frame;
pub(crate) use apply::{apply_to_problem, resync_mirror};
pub(crate) use plan::{Merge, RobotsPlan};
pub(crate) use session::in_robot_frame;

use super::batch::PreparedFactor;
use crate::api::robots::{ClosureReport, MergeReport, RobotReport, RobotsOptions, RobotsReport};
use crate::api::wire::FactorId;
use crate::problem::{Key, Variable};

/// The session's robots, components and held closures.
pub(crate) struct Robots {
    pub(crate) options: RobotsOptions,
    /// Union-find over keys; a key absent here is its own root.
    parent: HashMap<Key, Key>,
    /// Every component that holds a robot, by root. A root absent here holds none yet
    /// (landmarks, keys of no robot): it joins the first component a factor connects it to.
    components: HashMap<Key, Component>,
    robots: BTreeMap<u8, Robot>,
    /// Closures between components that hold robots and are not merged, by id: their keys.
    pending: BTreeMap<FactorId, Vec<Key>>,
    /// The held closures themselves, out of the problem until a merge takes them in.
    held: HashMap<FactorId, PreparedFactor>,
    /// Held closures admitted within one component after a merge, so far.
    admitted: u64,
    batches_since_check: u64,
    merges: Vec<MergeReport>,
    next_founding: u64,
}

#[derive(Clone, Debug)]
pub(crate) struct Component {
    robots: BTreeSet<u8>,
    /// Order of foundation: the older component keeps its frame in a merge.
    founded: u64,
}

#[derive(Clone, Debug)]
pub(crate) struct Robot {
    first: Key,
    poses: u64,
    /// Where its odometry frame sits in its component's frame (`component ← odom`).
    frame: Frame,
}

impl Robots {
    pub(crate) fn new(options: RobotsOptions) -> Self {
        Self {
            options,
            parent: HashMap::new(),
            components: HashMap::new(),
            robots: BTreeMap::new(),
            pending: BTreeMap::new(),
            held: HashMap::new(),
            admitted: 0,
            batches_since_check: 0,
            merges: Vec::new(),
            next_founding: 0,
        }
    }

    fn find(&self, mut key: Key) -> Key {
        while let Some(&p) = self.parent.get(&key) {
            if p == key {
                break;
            }
            key = p;
        }
        key
    }

    /// Joins the components of `a` and `b`; the older (or the one holding robots) stays root.
    fn union(&mut self, a: Key, b: Key) {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra == rb {
            return;
        }
        let (root, child) = match (self.components.get(&ra), self.components.get(&rb)) {
            (Some(x), Some(y)) if y.founded < x.founded => (rb, ra),
            (None, Some(_)) => (rb, ra),
            _ => (ra, rb),
        };
        self.parent.insert(child, root);
        if let Some(c) = self.components.remove(&child) {
            let r = self.components.entry(root).or_insert(Component {
                robots: BTreeSet::new(),
                founded: c.founded,
            });
            r.robots.extend(c.robots);
            r.founded = r.founded.min(c.founded);
        }
    }

    /// Every key whose root is `root` (a merge moves them all).
    fn members(&self, root: Key, keys: impl Iterator<Item = Key>) -> Vec<Key> {
        keys.filter(|&k| self.find(k) == root).collect()
    }

    /// Where robot `robot`'s odometry frame sits in its component (`None`: no such robot).
    pub(crate) fn frame_of(&self, robot: u8) -> Option<Frame> {
        self.robots.get(&robot).map(|r| r.frame)
    }

    /// `value` of `key` (in the map) in its robot's odometry frame, as the robot would have
    /// sent it; a copy of it for a key of no robot.
    pub(crate) fn in_odometry_frame(&self, key: Key, value: &dyn Variable) -> Box<dyn Variable> {
        let mut v = value.clone_box();
        if let Some(robot) = plan::robot_of(key, value).and_then(|r| self.robots.get(&r)) {
            robot.frame.inverse().apply(v.as_mut());
        }
        v
    }

    /// Forgets factors the client removed.
    pub(crate) fn remove_factors(&mut self, ids: &[FactorId]) {
        for id in ids {
            self.pending.remove(id);
            self.held.remove(id);
        }
    }

    /// Where each robot's odometry frame sat in its component once batch `sequence` was in:
    /// the merges up to it composed, the later ones not yet. Robots no merge moved by then
    /// (identity) are left out.
    pub(crate) fn frames_at(&self, sequence: u64) -> BTreeMap<u8, Frame> {
        let mut frames: BTreeMap<u8, Frame> = BTreeMap::new();
        for merge in self.merges.iter().filter(|m| m.sequence <= sequence) {
            let Some(moved_by) = Frame::from_wire(&merge.transform) else {
                continue;
            };
            for robot in merge.moved.iter().filter_map(|r| r.bytes().next()) {
                let frame = match frames.get(&robot) {
                    Some(earlier) => moved_by.compose(earlier).unwrap_or(moved_by),
                    None => moved_by,
                };
                frames.insert(robot, frame);
            }
        }
        frames
    }

    /// The robots' rows of the report: where each sits, without the held closures.
    pub(crate) fn robot_reports(&self) -> Vec<RobotReport> {
        let map_root = self
            .components
            .iter()
            .min_by_key(|(_, c)| c.founded)
            .map(|(root, _)| *root);
        self.robots
            .iter()
            .map(|(&r, robot)| {
                let root = self.find(robot.first);
                let component = self
                    .components
                    .get(&root)
                    .map(|c| c.robots.iter().map(|&c| (c as char).to_string()).collect())
                    .unwrap_or_default();
                RobotReport {
                    robot: (r as char).to_string(),
                    first_key: robot.first,
                    poses: robot.poses,
                    component,
                    in_map: Some(root) == map_root,
                    map_from_odom: robot.frame.to_wire(),
                }
            })
            .collect()
    }

    /// What `GET /v1/sessions/{s}/robots` shows.
    pub(crate) fn report(&self) -> RobotsReport {
        let robots = self.robot_reports();
        let (rejected, pending): (Vec<_>, Vec<_>) = self
            .pending
            .iter()
            .map(|(&id, keys)| {
                let within = self.placed_roots(keys).len() == 1;
                let reason = if within {
                    "within one component since a merge, but inconsistent with its map: held out, checked again as the map moves".to_string()
                } else {
                    self.pending_reason(keys)
                };
                (within, ClosureReport { factor_id: id, keys: keys.clone(), reason })
            })
            .partition(|(within, _)| *within);
        let strip = |v: Vec<(bool, ClosureReport)>| v.into_iter().map(|(_, c)| c).collect();
        let (pending, rejected) = (strip(pending), strip(rejected));
        RobotsReport {
            session: String::new(),
            robots,
            pending,
            rejected,
            merges: self.merges.clone(),
            admitted: self.admitted,
        }
    }

    fn pending_reason(&self, keys: &[Key]) -> String {
        let sides: BTreeSet<String> = keys
            .iter()
            .filter_map(|&k| self.components.get(&self.find(k)))
            .map(|c| c.robots.iter().map(|&r| r as char).collect())
            .collect();
        let waiting = self
            .pending
            .values()
            .filter(|other| {
                let mut roots: Vec<Key> = other.iter().map(|&k| self.find(k)).collect();
                let mut mine: Vec<Key> = keys.iter().map(|&k| self.find(k)).collect();
                roots.sort_unstable();
                roots.dedup();
                mine.sort_unstable();
                mine.dedup();
                roots == mine
            })
            .count();
        format!(
            "joins the components of robots {} not merged yet: {waiting} closure(s) between them, a merge needs {} that agree",
            sides.into_iter().collect::<Vec<_>>().join(" and "),
            self.options.min_closures
        )
    }
}
