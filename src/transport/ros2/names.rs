//! rmw_zenoh's names for the ROS 2 graph (rmw_zenoh_cpp `liveliness_utils.cpp`):
//!
//! - data: `<domain>/<topic without leading or trailing slash>/<dds type>/<type hash>`, e.g.
//!   `0/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_3cc9…`;
//! - liveliness tokens, what `ros2 node list` and `ros2 topic list` are built from:
//!   `@ros2_lv/<domain>/<zid>/<nid>/<eid>/<NN|MP|MS>/<enclave>/<namespace>/<node>` and, for an
//!   endpoint, `/<topic>/<dds type>/<type hash>/<qos>`, each component with `/` mangled to `%`
//!   (an empty namespace or enclave, `/`, becomes `%`);
//! - an entity's GID: XXH3-128 of its liveliness key expression, low 64 bits then high, in
//!   memory order (little endian).

use super::messages::RosType;

const ADMIN_SPACE: &str = "@ros2_lv";

/// An endpoint's QoS as rmw_zenoh writes it in the liveliness token, components equal to its
/// defaults (reliable, volatile, keep last, no deadline, lifespan or lease) left empty:
/// `<rel>:<dur>:<hist>,<depth>:<deadline s,ns>:<lifespan s,ns>:<liveliness>,<lease s>,<lease
/// ns>`, durability as rmw's enum (transient local 1).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Qos {
    /// Reliable, volatile, keep last 10: rclcpp's default profile (our subscriptions, the
    /// pose and `/tf`).
    Default,
    /// Reliable, transient local, keep last 1: a late subscriber gets the last sample (the
    /// path, as a map server latches its map).
    Latched,
}

impl Qos {
    pub fn keyexpr(self) -> &'static str {
        match self {
            Self::Default => "::,10:,:,:,,",
            Self::Latched => ":1:,1:,:,:,,",
        }
    }

    /// Samples a transient-local publisher keeps for late subscribers (its depth).
    pub fn cached_samples(self) -> Option<usize> {
        match self {
            Self::Default => None,
            Self::Latched => Some(1),
        }
    }
}

/// What an endpoint is in the graph.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EndpointKind {
    Publisher,
    Subscription,
    /// A service server.
    Service,
}

impl EndpointKind {
    fn code(self) -> &'static str {
        match self {
            Self::Publisher => "MP",
            Self::Subscription => "MS",
            Self::Service => "SS",
        }
    }
}

/// The node factord appears as: enclave `/`, its namespace (`/`, or a robot's: `/husky1`), its
/// id within our zenoh session.
#[derive(Clone, Debug)]
pub struct NodeName {
    pub domain_id: u32,
    /// Our zenoh session's id, as zenoh prints it (lowercase hex).
    pub zid: String,
    pub node_id: u64,
    pub namespace: String,
    pub name: String,
}

/// A ROS name made fully qualified (`odom` → `/odom`), as rmw_zenoh receives it from rcl.
pub fn fully_qualified(topic: &str) -> String {
    match topic.starts_with('/') {
        true => topic.to_string(),
        false => format!("/{topic}"),
    }
}

/// The key expression the samples of `topic` are put on.
pub fn topic_key(domain_id: u32, topic: &str, ros_type: &RosType) -> String {
    let topic = topic.trim_matches('/');
    format!(
        "{domain_id}/{topic}/{}/{}",
        ros_type.dds_name, ros_type.hash
    )
}

fn mangle(name: &str) -> String {
    name.replace('/', "%")
}

impl NodeName {
    fn prefix(&self, entity_id: u64, kind: &str) -> String {
        format!(
            "{ADMIN_SPACE}/{}/{}/{}/{entity_id}/{kind}/{}/{}/{}",
            self.domain_id,
            self.zid,
            self.node_id,
            mangle("/"),
            mangle(&self.namespace),
            mangle(&self.name)
        )
    }

    /// The node's own token: rmw_zenoh gives a node the entity id of its node id.
    pub fn node_token(&self) -> String {
        self.prefix(self.node_id, "NN")
    }

    pub fn endpoint_token(
        &self,
        entity_id: u64,
        kind: EndpointKind,
        topic: &str,
        ros_type: &RosType,
        qos: Qos,
    ) -> String {
        format!(
            "{}/{}/{}/{}/{}",
            self.prefix(entity_id, kind.code()),
            mangle(&fully_qualified(topic)),
            mangle(ros_type.dds_name),
            mangle(ros_type.hash),
            qos.keyexpr()
        )
    }
}

/// The GID rmw_zenoh derives from an entity's liveliness key expression.
pub fn gid_of(token: &str) -> [u8; 16] {
    let hash = xxhash_rust::xxh3::xxh3_128(token.as_bytes());
    let (low, high) = (hash as u64, (hash >> 64) as u64);
    let mut gid = [0u8; 16];
    gid[..8].copy_from_slice(&low.to_le_bytes());
    gid[8..].copy_from_slice(&high.to_le_bytes());
    gid
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transport::ros2::messages::{ODOMETRY, PATH};

    fn node() -> NodeName {
        NodeName {
            domain_id: 7,
            zid: "a1b2".into(),
            node_id: 3,
            namespace: "/".into(),
            name: "factord_s1".into(),
        }
    }

    #[test]
    fn keys_and_tokens_follow_rmw_zenoh() {
        assert_eq!(
            topic_key(7, "/robot1/odom", &ODOMETRY),
            "7/robot1/odom/nav_msgs::msg::dds_::Odometry_/\
             RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0"
        );
        assert_eq!(node().node_token(), "@ros2_lv/7/a1b2/3/3/NN/%/%/factord_s1");
        assert_eq!(
            node().endpoint_token(
                4,
                EndpointKind::Subscription,
                "robot1/odom",
                &ODOMETRY,
                Qos::Default
            ),
            "@ros2_lv/7/a1b2/3/4/MS/%/%/factord_s1/%robot1%odom/\
             nav_msgs::msg::dds_::Odometry_/\
             RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0/::,10:,:,:,,"
        );
        // Transient local (rmw's 1) and depth 1, as `ros2 topic pub --qos-durability
        // transient_local --qos-depth 1` declares it.
        let path = node().endpoint_token(5, EndpointKind::Publisher, "/path", &PATH, Qos::Latched);
        assert!(
            path.starts_with("@ros2_lv/7/a1b2/3/5/MP/%/%/factord_s1/%path/"),
            "{path}"
        );
        assert!(path.ends_with("/:1:,1:,:,:,,"), "{path}");
    }

    #[test]
    fn the_gid_is_xxh3_128_of_the_token_low_half_first() {
        // XXH3-128 of the empty input (the reference implementation's test vector):
        // 0x99aa06d3014798d86001c324468d497f.
        assert_eq!(
            gid_of(""),
            [
                0x7f, 0x49, 0x8d, 0x46, 0x24, 0xc3, 0x01, 0x60, 0xd8, 0x98, 0x47, 0x01, 0xd3, 0x06,
                0xaa, 0x99
            ]
        );
        // A token's length (166 bytes: XXH3's 129–240-byte path), against Python's `xxhash`.
        let token = node().endpoint_token(
            4,
            EndpointKind::Subscription,
            "robot1/odom",
            &ODOMETRY,
            Qos::Default,
        );
        let hash = u128::from_le_bytes(gid_of(&token));
        assert_eq!(hash, 0xfc64c9392215cf4663552217d8c49ddf);
    }
}
