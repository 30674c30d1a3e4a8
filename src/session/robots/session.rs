//! The session's side of its robots: turning them on at creation, the robots report, and a
//! journalled merge replayed.

use std::sync::Arc;

use std::collections::BTreeMap;

use super::{Frame, Robots, RobotsPlan};
use crate::api::catalogue;
use crate::api::robots::{
    robot_key, MergeRecord, RobotFrame, RobotReport, RobotsOptions, RobotsReport,
};
use crate::api::wire::{EstimateQuery, VariableValue, WireValue};
use crate::api::ServiceError;
use crate::session::Session;
use crate::session::State;

impl Session {
    /// Makes a new (empty) session hold several robots; pose graph kinds only.
    pub fn set_robots(&self, options: RobotsOptions) -> Result<(), ServiceError> {
        if !matches!(self.kind.name, "pose_graph_2d" | "pose_graph_3d") {
            return Err(ServiceError::bad_request(
                "invalid_value",
                "robots",
                format!(
                    "robots are for pose_graph_2d and pose_graph_3d sessions, not `{}`",
                    self.kind.name
                ),
            ));
        }
        if !(2..=64).contains(&options.min_closures) {
            return Err(ServiceError::bad_request(
                "invalid_value",
                "robots.min_closures",
                format!(
                    "min_closures is {}: a merge needs 2 to 64 agreeing closures (never one unchecked)",
                    options.min_closures
                ),
            ));
        }
        self.lock().robots = Some(Robots::new(options));
        Ok(())
    }

    pub fn robots_options(&self) -> Option<RobotsOptions> {
        self.lock().robots.as_ref().map(|r| r.options.clone())
    }

    /// `list_robots`; refused for a session without robots.
    pub fn robots_report(&self) -> Result<RobotsReport, ServiceError> {
        let st = self.lock();
        let Some(robots) = &st.robots else {
            return Err(self.no_robots());
        };
        Ok(RobotsReport {
            session: self.name.clone(),
            ..robots.report()
        })
    }

    /// Each robot's row of the robots report (where its frame sits, whether it is in the map),
    /// without the held closures the whole report lists; `None` for a session without robots.
    pub fn robot_reports(&self) -> Option<Vec<RobotReport>> {
        self.lock().robots.as_ref().map(Robots::robot_reports)
    }

    /// Each robot's `map ← odom` as it was once batch `sequence` was in, so that an estimate
    /// of that sequence is moved into the robots' odometry frames with the frames it was
    /// computed in, whatever merged since.
    pub fn odometry_frames_at(&self, sequence: u64) -> OdometryFrames {
        OdometryFrames(
            self.lock()
                .robots
                .as_ref()
                .map(|r| r.frames_at(sequence))
                .unwrap_or_default(),
        )
    }

    /// Checks an estimate read's `robot` and `frame`, and turns `robot` into its key range.
    pub fn resolve_robot_query(&self, query: &mut EstimateQuery) -> Result<(), ServiceError> {
        let Some(name) = query.robot.as_deref() else {
            if query.frame == Some(RobotFrame::Odom) {
                return Err(ServiceError::bad_request(
                    "invalid_value",
                    "frame",
                    "frame=odom reads one robot's poses in its own frame: name the robot (robot=b)",
                ));
            }
            return Ok(());
        };
        let robot = match name.as_bytes() {
            [c] if c.is_ascii_graphic() => *c,
            _ => {
                return Err(ServiceError::bad_request(
                    "invalid_value",
                    "robot",
                    format!(
                        "robot `{name}` is not one printable ASCII character (its keys' top byte)"
                    ),
                ))
            }
        };
        if query.from.is_some() || query.to.is_some() {
            return Err(ServiceError::bad_request(
                "invalid_value",
                "robot",
                "robot selects its own keys: give it without from/to",
            ));
        }
        let st = self.lock();
        let Some(robots) = &st.robots else {
            return Err(self.no_robots());
        };
        if robots.frame_of(robot).is_none() {
            let mut e = ServiceError::not_found("robot", name);
            e.body.message = format!(
                "session `{}` has no robot `{name}` (none of its poses arrived)",
                self.name
            );
            return Err(e.at("robot"));
        }
        query.from = Some(robot_key(robot as char, 0));
        query.to = Some(robot_key(robot as char, (1 << 56) - 1));
        Ok(())
    }

    fn no_robots(&self) -> ServiceError {
        ServiceError::bad_request(
            "no_robots",
            "session",
            format!(
                "session `{}` was not created with `robots`: it holds one robot's map",
                self.name
            ),
        )
    }

    /// Applies a merge the journal recorded after batch `sequence` (recovery, adoption).
    pub(crate) fn replay_merge(
        self: &Arc<Self>,
        sequence: u64,
        record: MergeRecord,
    ) -> Result<(), String> {
        let mut st = self.lock();
        let st = &mut *st;
        let Some(robots) = st.robots.as_mut() else {
            return Err("a merge record in a session without robots".into());
        };
        let mut plan = RobotsPlan::default();
        robots
            .apply_record(record, sequence, 0.0, &mut st.mirror.entries, &mut plan)
            .ok_or("a merge record that does not fit the session's held closures")?;
        let (Some(problem), Some(index)) = (st.model.problem.as_mut(), st.model.index.as_mut())
        else {
            return Err("a merge record replayed while the problem is out".into());
        };
        let first = problem.factors().len();
        let moved = super::apply_to_problem(problem, &mut st.model.factor_ids, plan.merges);
        index.extend(problem, first);
        super::resync_mirror(problem, &mut st.mirror.entries, &moved);
        st.schedule.structural = true;
        st.schedule.phase.mark_dirty();
        st.results.converged = false;
        Ok(())
    }
}

/// Where the robots' odometry frames sat in the map at some sequence (robots no merge had
/// moved by then are where they started: identity).
pub struct OdometryFrames(BTreeMap<u8, Frame>);

impl OdometryFrames {
    /// `variables` (robot `robot`'s, in the map) moved into its odometry frame.
    pub fn move_into(&self, robot: u8, variables: &mut [VariableValue]) {
        if let Some(map_from_odom) = self.0.get(&robot) {
            into_odometry_frame(map_from_odom, variables);
        }
    }
}

/// `variables` (one robot's poses, `query.robot`) moved into the robot's own odometry frame
/// when `query.frame` asks for it.
pub(crate) fn in_robot_frame(st: &State, query: &EstimateQuery, variables: &mut [VariableValue]) {
    let (Some(RobotFrame::Odom), Some(&[robot])) =
        (query.frame, query.robot.as_deref().map(str::as_bytes))
    else {
        return;
    };
    let Some(map_from_odom) = st.robots.as_ref().and_then(|r| r.frame_of(robot)) else {
        return;
    };
    into_odometry_frame(&map_from_odom, variables);
}

/// `variables` (one robot's, in the map) moved into that robot's odometry frame, which sits at
/// `map_from_odom` in the map; kinds a frame does not move are left as they are.
fn into_odometry_frame(map_from_odom: &Frame, variables: &mut [VariableValue]) {
    let to_odom = map_from_odom.inverse();
    for v in variables {
        let Some(Ok(mut value)) = catalogue::variable_codec(&v.kind).map(|c| (c.decode)(&v.value))
        else {
            continue;
        };
        if to_odom.apply(value.as_mut()) {
            v.value = WireValue::from_vec(catalogue::encode_variable(value.as_ref()));
        }
    }
}
