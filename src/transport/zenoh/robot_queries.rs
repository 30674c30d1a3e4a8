//! The queryables of a robot's own keys (see `robot_streams` for its publications):
//! - `<p>/<s>/robot/<id>/estimate`: the robot's estimate, as `estimate?robot=<id>` answers it;
//!   selector parameters `frame` (`map`, default, or `odom`), `since`, `format` as on HTTP.
//!   `robot`, `from` and `to` are the key's to say: given, they are refused (`robot`).
//! - `<p>/<s>/robot/<id>/map_from_odom`: where the robot's odometry frame sits in the map now
//!   ([`RobotFrameReport`]), for a robot that subscribes after the last change was published.
//!
//! An `<id>` that is no robot id (see [`parse_robot_id`]) is refused 400-like `invalid_value`
//! at `robot`, a robot the session does not hold `unknown_robot` at `robot`, both as error
//! replies (`{"error": {…}}`) as every queryable's.

use zenoh::query::Query;

use super::{reply, Context};
use crate::api::robots::{parse_robot_id, RobotFrameReport};
use crate::api::wire::EstimateQuery;
use crate::api::ListRobots;
use crate::service::{parse_query, Command, Recording, Reply, ServiceError};

/// The session and the robot a robot key names: `<p>/<s>/robot/<id>/<what>`.
fn session_and_robot(query: &Query) -> Result<(String, u8), ServiceError> {
    let key = query.key_expr().as_str();
    let mut chunks = key.rsplit('/');
    let (_what, id, robot, session) = (chunks.next(), chunks.next(), chunks.next(), chunks.next());
    let (Some(id), Some("robot"), Some(session)) = (id, robot, session) else {
        return Err(ServiceError::bad_request(
            "invalid_key",
            "key",
            "expected <prefix>/<session>/robot/<id>/<estimate|map_from_odom>",
        ));
    };
    let robot = parse_robot_id(id).ok_or_else(|| {
        ServiceError::bad_request(
            "invalid_value",
            "robot",
            format!(
                "`{id}` in the key is no robot id: a robot's character (a letter or a digit), \
                 or `x` and the two hex digits of another printable character (`x2a` for `*`)"
            ),
        )
    })?;
    Ok((session.to_string(), robot))
}

/// `<p>/<s>/robot/<id>/estimate`.
pub(super) async fn answer_robot_estimate(c: &Context, query: &Query) {
    super::answer_estimate_command(c, query, robot_estimate_command(query)).await;
}

fn robot_estimate_command(query: &Query) -> Result<Command, ServiceError> {
    let (session, robot) = session_and_robot(query)?;
    let mut estimate: EstimateQuery = parse_query(query.parameters().as_str())?;
    if estimate.robot.is_some() || estimate.from.is_some() || estimate.to.is_some() {
        return Err(ServiceError::bad_request(
            "invalid_value",
            "robot",
            "the key names the robot: give no robot, from or to in the selector",
        ));
    }
    estimate.robot = Some((robot as char).to_string());
    Ok(Command::get_estimate(session, estimate))
}

/// `<p>/<s>/robot/<id>/map_from_odom`.
pub(super) async fn answer_robot_frame(c: &Context, query: &Query) {
    let result = match session_and_robot(query) {
        Ok((session, robot)) => robot_frame(c, session, robot).await,
        Err(e) => Err(e),
    };
    reply(query, result.map(|r| serde_json::to_vec(&r))).await;
}

async fn robot_frame(
    c: &Context,
    session: String,
    robot: u8,
) -> Result<RobotFrameReport, ServiceError> {
    let command = Command::ListRobots(ListRobots {
        session: session.clone(),
    });
    let reply = c
        .service
        .execute(&c.caller, command, Recording::History)
        .await?;
    let Reply::Robots(report) = reply else {
        return Err(ServiceError::internal(
            "list_robots answered something else",
        ));
    };
    let name = (robot as char).to_string();
    let found = report.robots.into_iter().find(|r| r.robot == name);
    match found {
        Some(robot) => Ok(RobotFrameReport { session, robot }),
        None => {
            let mut e = ServiceError::not_found("robot", &name);
            e.body.message =
                format!("session `{session}` has no robot `{name}` (none of its poses arrived)");
            Err(e.at("robot"))
        }
    }
}
