//! RIHS01 type hashes computed from `.msg` IDL exactly as rosidl does (REP-2011;
//! `rosidl_generator_type_description`): the type description — the type's fields and, sorted
//! by name, every type it refers to, each field as `type_id`, `capacity`, `string_capacity`,
//! `nested_type_name` — serialised as Python's `json.dumps` writes it (separators `", "` and
//! `": "`, keys in declaration order, no default values, no constants, no comments) and hashed
//! with SHA-256.
//!
//! rmw_zenoh puts the hash in every key expression and liveliness token: a wrong hash is a
//! robot that never hears us. The standard messages' hashes in `messages` came from real ROS
//! Jazzy; the tests recompute them here from their `.msg` definitions (`idl/`), byte for byte,
//! and the same code hashes our own `factord_msgs` (`clients/ros2/factord_msgs`).
//!
//! `.msg` as rosidl reads it: a field is `type name [default]`; a constant is `type NAME=value`;
//! `Header` is `std_msgs/Header`; an unqualified type is of the same package; `T[N]` is a fixed
//! array (type id + 48), `T[<=N]` a bounded sequence (+ 96), `T[]` a sequence (+ 144);
//! `string<=N` a bounded string. rosidl converts `.msg` to IDL first, which maps `char` to
//! `uint8` and `byte` to `octet`: their type ids are those.

use std::collections::BTreeMap;

/// One interface definition: its full name (`nav_msgs/msg/Odometry`) and `.msg` text.
pub type Definition<'a> = (&'a str, &'a str);

macro_rules! std_def {
    ($package:literal, $name:literal) => {
        (
            concat!($package, "/msg/", $name),
            include_str!(concat!("idl/", $package, "/msg/", $name, ".msg")),
        )
    };
}
/// The standard messages the binding speaks, as in ROS Jazzy (fields only: constants and
/// comments do not enter the hash). Written from the Jazzy definitions as `rosbags` 0.11.9's
/// type store holds them.
pub const STANDARD: &[Definition<'static>] = &[
    std_def!("builtin_interfaces", "Duration"),
    std_def!("builtin_interfaces", "Time"),
    std_def!("geometry_msgs", "Point"),
    std_def!("geometry_msgs", "Pose"),
    std_def!("geometry_msgs", "PoseStamped"),
    std_def!("geometry_msgs", "PoseWithCovariance"),
    std_def!("geometry_msgs", "PoseWithCovarianceStamped"),
    std_def!("geometry_msgs", "Quaternion"),
    std_def!("geometry_msgs", "Transform"),
    std_def!("geometry_msgs", "TransformStamped"),
    std_def!("geometry_msgs", "Twist"),
    std_def!("geometry_msgs", "TwistWithCovariance"),
    std_def!("geometry_msgs", "Vector3"),
    std_def!("service_msgs", "ServiceEventInfo"),
    std_def!("nav_msgs", "Odometry"),
    std_def!("nav_msgs", "Path"),
    std_def!("sensor_msgs", "CompressedImage"),
    std_def!("sensor_msgs", "Imu"),
    std_def!("std_msgs", "ColorRGBA"),
    std_def!("std_msgs", "Header"),
    std_def!("tf2_msgs", "TFMessage"),
    std_def!("visualization_msgs", "Marker"),
    std_def!("visualization_msgs", "MarkerArray"),
    std_def!("visualization_msgs", "MeshFile"),
    std_def!("visualization_msgs", "UVCoordinate"),
];

/// Our own interface package, as robots build it in their workspace.
pub const FACTORD_MSGS: &[Definition<'static>] = &[
    (
        "factord_msgs/msg/LoopClosure",
        include_str!("../../../clients/ros2/factord_msgs/msg/LoopClosure.msg"),
    ),
    (
        "factord_msgs/msg/LandmarkSighting",
        include_str!("../../../clients/ros2/factord_msgs/msg/LandmarkSighting.msg"),
    ),
    (
        "factord_msgs/msg/RobotLoopClosure",
        include_str!("../../../clients/ros2/factord_msgs/msg/RobotLoopClosure.msg"),
    ),
];

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum TypeHashError {
    #[error("{0}: no definition of this type is known")]
    Unknown(String),
    #[error("{type_name} line {line}: {reason}")]
    Syntax {
        type_name: String,
        line: usize,
        reason: String,
    },
}

/// `RIHS01_<64 hex digits>` of `type_name`, whose definition and every type it refers to are
/// among `definitions`.
pub fn rihs01(type_name: &str, definitions: &[Definition]) -> Result<String, TypeHashError> {
    let mut described = BTreeMap::new();
    describe(type_name, definitions, &mut described)?;
    let own = described
        .remove(type_name)
        .expect("describe put the type itself in");
    // BTreeMap: referenced types sorted by name, as rosidl sorts them.
    let referenced: Vec<String> = described.into_values().collect();
    let json = format!(
        "{{\"type_description\": {own}, \"referenced_type_descriptions\": [{}]}}",
        referenced.join(", ")
    );
    let digest = ring::digest::digest(&ring::digest::SHA256, json.as_bytes());
    let hex: String = digest.as_ref().iter().map(|b| format!("{b:02x}")).collect();
    Ok(format!("RIHS01_{hex}"))
}

/// `std_srvs/srv/Trigger` (Jazzy).
pub const TRIGGER: Definition<'static> = (
    "std_srvs/srv/Trigger",
    include_str!("idl/std_srvs/srv/Trigger.srv"),
);

/// The RIHS01 hash of a service (`std_srvs/srv/Trigger` and its `.srv` text): as rosidl
/// describes a service, a type of three fields `request_message`, `response_message` and
/// `event_message`, the last `<Service>_Event { service_msgs/ServiceEventInfo info;
/// <Service>_Request[<=1] request; <Service>_Response[<=1] response }`.
pub fn service_rihs01(
    (service, text): Definition,
    definitions: &[Definition],
) -> Result<String, TypeHashError> {
    let lines: Vec<&str> = text.lines().collect();
    let split = lines
        .iter()
        .position(|line| line.trim() == "---")
        .ok_or_else(|| TypeHashError::Syntax {
            type_name: service.into(),
            line: lines.len(),
            reason: "a service has a request and a response separated by `---`".into(),
        })?;
    let (request, response) = (lines[..split].join("\n"), lines[split + 1..].join("\n"));
    let names = ["Request", "Response", "Event"].map(|part| format!("{service}_{part}"));
    let [request_name, response_name, event_name] = &names;
    let event = format!(
        "service_msgs/ServiceEventInfo info\n{request_name}[<=1] request\n\
         {response_name}[<=1] response\n"
    );
    let own = format!(
        "{request_name} request_message\n{response_name} response_message\n\
         {event_name} event_message\n"
    );
    let mut all: Vec<Definition> = definitions.to_vec();
    all.extend([
        (service, own.as_str()),
        (request_name.as_str(), request.as_str()),
        (response_name.as_str(), response.as_str()),
        (event_name.as_str(), event.as_str()),
    ]);
    rihs01(service, &all)
}

/// Puts the JSON description of `type_name` and of every type it refers to into `described`.
fn describe(
    type_name: &str,
    definitions: &[Definition],
    described: &mut BTreeMap<String, String>,
) -> Result<(), TypeHashError> {
    if described.contains_key(type_name) {
        return Ok(());
    }
    let (_, text) = definitions
        .iter()
        .find(|(name, _)| *name == type_name)
        .ok_or_else(|| TypeHashError::Unknown(type_name.into()))?;
    let package = type_name.split('/').next().unwrap_or_default();
    let mut fields = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let syntax = |reason: String| TypeHashError::Syntax {
            type_name: type_name.into(),
            line: i + 1,
            reason,
        };
        if let Some(field) = parse_line(line, package).map_err(syntax)? {
            fields.push(field);
        }
    }
    if fields.is_empty() {
        // rosidl gives an empty message one member (C structs cannot be empty).
        fields.push(Field {
            name: "structure_needs_at_least_one_member".into(),
            type_id: UINT8,
            capacity: 0,
            string_capacity: 0,
            nested: None,
        });
    }
    // Placeholder first: a type that refers to itself (not possible in ROS) cannot loop.
    described.insert(type_name.into(), String::new());
    for nested in fields.iter().filter_map(|f| f.nested.as_deref()) {
        describe(nested, definitions, described)?;
    }
    let fields: Vec<String> = fields.iter().map(Field::json).collect();
    let json = format!(
        "{{\"type_name\": {}, \"fields\": [{}]}}",
        json_string(type_name),
        fields.join(", ")
    );
    described.insert(type_name.into(), json);
    Ok(())
}

const NESTED: u8 = 1;
const UINT8: u8 = 3;
const STRING: u8 = 17;
const WSTRING: u8 = 18;
const BOUNDED_STRING: u8 = 21;
const BOUNDED_WSTRING: u8 = 22;
const ARRAY: u8 = 48;
const BOUNDED_SEQUENCE: u8 = 96;
const UNBOUNDED_SEQUENCE: u8 = 144;

/// `type_description_interfaces/msg/FieldType`'s ids of the primitive types, by `.msg` name
/// (`char` and `byte` as rosidl's `.msg` → IDL conversion makes them: `uint8`, `octet`).
fn primitive(name: &str) -> Option<u8> {
    Some(match name {
        "int8" => 2,
        "uint8" | "char" => UINT8,
        "int16" => 4,
        "uint16" => 5,
        "int32" => 6,
        "uint32" => 7,
        "int64" => 8,
        "uint64" => 9,
        "float32" => 10,
        "float64" => 11,
        "bool" => 15,
        "byte" => 16,
        "string" => STRING,
        "wstring" => WSTRING,
        _ => return None,
    })
}

struct Field {
    name: String,
    type_id: u8,
    capacity: u64,
    string_capacity: u64,
    nested: Option<String>,
}

impl Field {
    fn json(&self) -> String {
        format!(
            "{{\"name\": {}, \"type\": {{\"type_id\": {}, \"capacity\": {}, \
             \"string_capacity\": {}, \"nested_type_name\": {}}}}}",
            json_string(&self.name),
            self.type_id,
            self.capacity,
            self.string_capacity,
            json_string(self.nested.as_deref().unwrap_or_default())
        )
    }
}

/// Python's `json.dumps` of a string with `ensure_ascii` (non-ASCII as `\uXXXX`).
fn json_string(s: &str) -> String {
    let mut out = String::from("\"");
    for unit in s.encode_utf16() {
        match unit {
            0x22 => out.push_str("\\\""),
            0x5c => out.push_str("\\\\"),
            0x0a => out.push_str("\\n"),
            0x0d => out.push_str("\\r"),
            0x09 => out.push_str("\\t"),
            0x08 => out.push_str("\\b"),
            0x0c => out.push_str("\\f"),
            0x20..=0x7e => out.push(char::from(unit as u8)),
            _ => out.push_str(&format!("\\u{unit:04x}")),
        }
    }
    out.push('"');
    out
}

/// A field of a `.msg` line; `None` for a blank line, a comment or a constant.
fn parse_line(line: &str, package: &str) -> Result<Option<Field>, String> {
    let line = line.trim();
    if line.is_empty() || line.starts_with('#') {
        return Ok(None);
    }
    let (type_text, rest) = line
        .split_once(char::is_whitespace)
        .ok_or_else(|| format!("`{line}`: a type and a name are expected"))?;
    let rest = rest.trim_start();
    let name_end = rest
        .find(|c: char| c.is_whitespace() || c == '=' || c == '#')
        .unwrap_or(rest.len());
    let (name, after) = rest.split_at(name_end);
    if name.is_empty() {
        return Err(format!("`{line}`: a field name is expected"));
    }
    if after.trim_start().starts_with('=') {
        return Ok(None); // a constant: not part of the type description
    }
    let (base, container) = match type_text.split_once('[') {
        None => (type_text, None),
        Some((base, bracket)) => {
            let inner = bracket
                .strip_suffix(']')
                .ok_or_else(|| format!("`{type_text}`: an array type ends with `]`"))?;
            (base, Some(inner))
        }
    };
    let number = |text: &str| {
        text.parse::<u64>()
            .map_err(|_| format!("`{type_text}`: `{text}` is not a size"))
    };
    let (mut type_id, mut string_capacity, nested) = match base.split_once("<=") {
        Some(("string", bound)) => (BOUNDED_STRING, number(bound)?, None),
        Some(("wstring", bound)) => (BOUNDED_WSTRING, number(bound)?, None),
        Some(_) => return Err(format!("`{base}`: only strings have bounds")),
        None => match primitive(base) {
            Some(id) => (id, 0, None),
            None => (NESTED, 0, Some(nested_name(base, package)?)),
        },
    };
    let capacity = match container {
        None => 0,
        Some("") => {
            type_id += UNBOUNDED_SEQUENCE;
            0
        }
        Some(bound) => match bound.strip_prefix("<=") {
            Some(bound) => {
                type_id += BOUNDED_SEQUENCE;
                number(bound)?
            }
            None => {
                type_id += ARRAY;
                number(bound)?
            }
        },
    };
    if nested.is_some() {
        string_capacity = 0;
    }
    Ok(Some(Field {
        name: name.into(),
        type_id,
        capacity,
        string_capacity,
        nested,
    }))
}

/// The full name of a message type a field names: `Header`, `pkg/Name`, or `Name` of the same
/// package.
fn nested_name(base: &str, package: &str) -> Result<String, String> {
    let valid = |s: &str| {
        !s.is_empty()
            && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
            && !s.starts_with(|c: char| c.is_ascii_digit())
    };
    match base.split('/').collect::<Vec<_>>()[..] {
        ["Header"] => Ok("std_msgs/msg/Header".into()),
        // Already full, as the parts of a service are (`std_srvs/srv/Trigger_Request`).
        [pkg, kind, name] if valid(pkg) && valid(kind) && valid(name) => {
            Ok(format!("{pkg}/{kind}/{name}"))
        }
        [name] if valid(name) => Ok(format!("{package}/msg/{name}")),
        [pkg, name] if valid(pkg) && valid(name) => Ok(format!("{pkg}/msg/{name}")),
        _ => Err(format!("`{base}` is not a type name")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transport::ros2::messages::{
        IMU, MARKER_ARRAY, ODOMETRY, PATH, POSE_WITH_COVARIANCE_STAMPED, TF_MESSAGE,
    };

    #[test]
    fn the_standard_hashes_from_ros_jazzy_are_recomputed_from_their_msg_files() {
        for known in [
            ODOMETRY,
            POSE_WITH_COVARIANCE_STAMPED,
            IMU,
            TF_MESSAGE,
            PATH,
            MARKER_ARRAY,
        ] {
            assert_eq!(
                rihs01(known.name, STANDARD).unwrap(),
                known.hash,
                "{}",
                known.name
            );
        }
    }

    /// The hash ROS Jazzy's `std_srvs` gives Trigger (as rmw_zenoh keys of real Trigger
    /// services carry it, and as independent RIHS01 implementations' tests hold it): the
    /// service form and `char` → `uint8` (in `ServiceEventInfo.client_gid`) are rosidl's.
    #[test]
    fn the_trigger_service_hash_is_jazzys() {
        assert_eq!(
            service_rihs01(TRIGGER, STANDARD).unwrap(),
            "RIHS01_eeff2cd6fa5ad9d27cdf4dec64818317839b62f212a91e6b5304b634b2062c5f"
        );
    }

    #[test]
    fn the_description_is_rosidls_json_form() {
        const TIME: &[Definition] = &[(
            "builtin_interfaces/msg/Time",
            "# comment\nint32 sec\nuint32 nanosec # trailing\nint32 ZERO=0\n",
        )];
        let mut described = BTreeMap::new();
        describe("builtin_interfaces/msg/Time", TIME, &mut described).unwrap();
        assert_eq!(
            described["builtin_interfaces/msg/Time"],
            "{\"type_name\": \"builtin_interfaces/msg/Time\", \"fields\": [\
             {\"name\": \"sec\", \"type\": {\"type_id\": 6, \"capacity\": 0, \
             \"string_capacity\": 0, \"nested_type_name\": \"\"}}, \
             {\"name\": \"nanosec\", \"type\": {\"type_id\": 7, \"capacity\": 0, \
             \"string_capacity\": 0, \"nested_type_name\": \"\"}}]}"
        );
    }

    #[test]
    fn containers_bounds_and_defaults_have_their_ids() {
        let field = |line| parse_line(line, "pkg").unwrap().unwrap();
        let f = field("float64[36] covariance");
        assert_eq!((f.type_id, f.capacity), (11 + 48, 36));
        let f = field("Point[<=5] points");
        assert_eq!((f.type_id, f.capacity), (1 + 96, 5));
        assert_eq!(f.nested.as_deref(), Some("pkg/msg/Point"));
        let f = field("string<=8[] names");
        assert_eq!((f.type_id, f.string_capacity), (21 + 144, 8));
        let f = field("bool flag false # a default does not enter the hash");
        assert_eq!((f.name.as_str(), f.type_id), ("flag", 15));
        assert!(parse_line("string NAME = \"a#b\"", "pkg")
            .unwrap()
            .is_none());
        assert!(parse_line("float64", "pkg").is_err());
        assert!(parse_line("float64[x] v", "pkg").is_err());
        assert_eq!(
            rihs01("pkg/msg/Missing", &[("pkg/msg/A", "B b\n")]),
            Err(TypeHashError::Unknown("pkg/msg/Missing".into()))
        );
    }

    #[test]
    fn our_messages_hash_and_refer_only_to_standard_types() {
        let all: Vec<Definition> = STANDARD.iter().chain(FACTORD_MSGS).copied().collect();
        // As rosbags 0.11.9 hashes them (`get_types_from_msg`, `hash_rihs01`), an
        // implementation of rosidl's algorithm other than ours.
        let rosbags = [
            (
                "factord_msgs/msg/LoopClosure",
                "RIHS01_ed4e073c82f27c81a0c5bd0b4aa0df8b5318be492df7295f4621c67150383c7b",
            ),
            (
                "factord_msgs/msg/LandmarkSighting",
                "RIHS01_08a475e9bf882af6b2778dde375da38024c33a3a814093c79a8196ed4bb46130",
            ),
            (
                "factord_msgs/msg/RobotLoopClosure",
                "RIHS01_27ec86e854e91f7c625cd34bc65021feca41e214b19f5e93ea67c87a31bb7562",
            ),
        ];
        for (name, hash) in rosbags {
            assert_eq!(rihs01(name, &all).unwrap(), hash, "{name}");
        }
    }
}
