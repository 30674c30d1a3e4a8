//! The session's side of its robots: turning them on at creation, the robots report, and a
//! journalled merge replayed.

use std::sync::Arc;

use super::{Robots, RobotsPlan};
use crate::api::robots::{MergeRecord, RobotsOptions, RobotsReport};
use crate::api::ServiceError;
use crate::session::Session;

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
            return Err(ServiceError::bad_request(
                "no_robots",
                "session",
                format!(
                    "session `{}` was not created with `robots`: it holds one robot's map",
                    self.name
                ),
            ));
        };
        let (robots, pending, rejected, merges) = robots.report();
        Ok(RobotsReport {
            session: self.name.clone(),
            robots,
            pending,
            rejected,
            merges,
        })
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
            .merge(record, sequence, 0.0, &mut st.mirror.entries, &mut plan)
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
