//! Robots in one session, as the wire shows them: the option that makes a session hold several
//! robots, what `GET /v1/sessions/{s}/robots` answers, and the `merge` event.
//!
//! A robot is named by its keys, as GTSAM's `Symbol` does: key `(c << 56) | i` is pose `i` of
//! robot `c`, one printable ASCII character (`'a'`, `'b'`, …). A robot's values arrive in its own
//! odometry frame; its poses form a component of the map of their own until closures to another
//! robot's poses merge the two (see `session::robots`).

use serde::{Deserialize, Serialize};

use super::wire::FactorId;
use crate::problem::Key;

/// `robots` at session creation: the session holds several robots, each in its own frame until
/// a merge.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct RobotsOptions {
    /// How many mutually consistent closures between two components merge them (2 or more:
    /// never one unchecked closure). Default 3.
    #[serde(default = "default_min_closures")]
    pub min_closures: usize,
}

fn default_min_closures() -> usize {
    3
}

impl Default for RobotsOptions {
    fn default() -> Self {
        Self {
            min_closures: default_min_closures(),
        }
    }
}

/// Which frame a robot's estimate is read in (`estimate?robot=b&frame=odom`).
#[derive(Clone, Copy, Debug, Default, Deserialize, Serialize, PartialEq, Eq, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum RobotFrame {
    /// The map: where the session's estimate is (the first robot's odometry frame).
    #[default]
    Map,
    /// The robot's own odometry frame, as it sent its values (`map_from_odom⁻¹ ∘ pose`).
    Odom,
}

/// The robot a key names: its top byte when that is a printable ASCII character.
pub fn robot_of_key(key: Key) -> Option<char> {
    let c = (key >> 56) as u8;
    c.is_ascii_graphic().then_some(c as char)
}

/// The key of pose `index` of robot `robot` (GTSAM's `Symbol(robot, index)`).
pub fn robot_key(robot: char, index: u64) -> Key {
    ((robot as u64) << 56) | (index & ((1 << 56) - 1))
}

/// How robot `robot` is named where a name must be a key expression chunk or a ROS name
/// (`<p>/<s>/robot/<id>/…` on zenoh, `robot_<id>/odom` on `/tf`): its character when that is
/// an ASCII letter or digit, else `x` and the character's two hex digits (robot `*` is `x2a`;
/// one character and three never collide).
pub fn robot_id(robot: u8) -> String {
    match robot.is_ascii_alphanumeric() {
        true => (robot as char).to_string(),
        false => format!("x{robot:02x}"),
    }
}

/// The robot a [`robot_id`] names, or `None` when it is no such name.
pub fn parse_robot_id(id: &str) -> Option<u8> {
    match id.as_bytes() {
        [c] if c.is_ascii_alphanumeric() => Some(*c),
        [b'x', hex @ ..] if hex.len() == 2 => u8::from_str_radix(id.get(1..)?, 16)
            .ok()
            .filter(|c| c.is_ascii_graphic() && !c.is_ascii_alphanumeric()),
        _ => None,
    }
}

/// One robot's place in the map, as `<p>/<s>/robot/<id>/map_from_odom` carries it on zenoh
/// (published when it changes, and answered to a query): its row of the robots report.
#[derive(Clone, Debug, Serialize, Deserialize, utoipa::ToSchema)]
pub struct RobotFrameReport {
    pub session: String,
    #[serde(flatten)]
    pub robot: RobotReport,
}

/// A merge as the journal records it (with the batch that completed it), so a replay applies
/// the decision instead of taking it again on a different estimate.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MergeRecord {
    /// The agreeing closures that enter the map; the first names the two components.
    pub closures: Vec<FactorId>,
    /// The held closures between the two components that disagree with them.
    pub rejected: Vec<FactorId>,
    /// `kept ← moved`, as [`RobotReport::map_from_odom`].
    pub transform: Vec<f64>,
}

/// `GET /v1/sessions/{s}/robots`.
#[derive(Clone, Debug, Serialize, Deserialize, utoipa::ToSchema)]
pub struct RobotsReport {
    pub session: String,
    pub robots: Vec<RobotReport>,
    /// Closures between components not merged yet: held out of the map until enough of them
    /// agree.
    pub pending: Vec<ClosureReport>,
    /// Closures the merge found inconsistent with the others: kept out of the map.
    pub rejected: Vec<ClosureReport>,
    /// Every merge so far, oldest first.
    pub merges: Vec<MergeReport>,
    /// Closures held at a merge (they disagreed with the closures that decided it) that later
    /// fit the merged map and entered it.
    pub admitted: u64,
}

#[derive(Clone, Debug, Serialize, Deserialize, utoipa::ToSchema)]
pub struct RobotReport {
    /// The robot's character (`"a"`).
    pub robot: String,
    /// Its first pose's key.
    pub first_key: Key,
    pub poses: u64,
    /// The robots whose poses share this robot's frame of reference (itself included); the
    /// map is the component of the robot seen first.
    pub component: Vec<String>,
    /// Whether its component holds the robot seen first (its poses are in the map frame).
    pub in_map: bool,
    /// Where its odometry frame sits in its component's frame: `[x, y, θ]` or
    /// `[x, y, z, qx, qy, qz, qw]` (`map ← odom`, identity until a merge moves it).
    pub map_from_odom: Vec<f64>,
}

#[derive(Clone, Debug, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ClosureReport {
    pub factor_id: FactorId,
    pub keys: Vec<Key>,
    /// Why it is pending or rejected.
    pub reason: String,
}

/// A merge of two components (also the `merge` event).
#[derive(Clone, Debug, Serialize, Deserialize, utoipa::ToSchema)]
pub struct MergeReport {
    /// The sequence of the batch whose closures completed the merge.
    pub sequence: u64,
    /// The robots of the component that kept its frame, and of the one moved into it.
    pub kept: Vec<String>,
    pub moved: Vec<String>,
    /// The transform that moved them (`kept ← moved`), as `map_from_odom`.
    pub transform: Vec<f64>,
    /// The closures it was found from (now in the map), and those it rejected.
    pub closures: Vec<FactorId>,
    pub rejected: Vec<FactorId>,
    /// Time spent deciding it (consistency, alignment), in seconds.
    pub seconds: f64,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_name_robots_as_gtsam_symbols_do() {
        let k = robot_key('b', 42);
        assert_eq!(k, 7061644215716937770);
        assert_eq!(robot_of_key(k), Some('b'));
        assert_eq!(robot_of_key(42), None);
        assert_eq!(k & 0xff_ffff_ffff_ffff, 42);
    }

    #[test]
    fn robot_ids_are_key_chunks_and_name_one_robot_each() {
        for robot in 0x21u8..0x7f {
            let id = robot_id(robot);
            assert!(id.bytes().all(|b| b.is_ascii_alphanumeric()), "{id}");
            assert_eq!(parse_robot_id(&id), Some(robot), "{id}");
        }
        assert_eq!(robot_id(b'*'), "x2a");
        for bad in ["", "ab", "x41", "x2", "x2g", "*", "x7f", "é"] {
            assert_eq!(parse_robot_id(bad), None, "{bad}");
        }
    }
}
