//! ROS 2 input bounds (issue 52, items 5 and 11): a real `factord serve` bound to ROS topics,
//! a zenoh peer that puts CDR bytes on the topics' key expressions as rmw_zenoh does (written
//! here field by field, so that they can also be wrong in ways no ROS library writes), and the
//! refusals read on the session's `out/errors`. After each refusal the session must hold only
//! what the good messages made.

use crate::common;

use std::time::Duration;

use common::server::{client, create, get, holders, post, ros_nodes_until, zenoh_peer, TestServer};
use serde_json::{json, Value};
use zenoh::handlers::FifoChannelHandler;
use zenoh::pubsub::Subscriber;
use zenoh::sample::Sample;

const ODOMETRY: &str =
    "nav_msgs::msg::dds_::Odometry_/RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0";
const PRIOR: &str = "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e";

/// CDR little endian with its encapsulation header, aligned from the end of that header.
struct Cdr(Vec<u8>);

impl Cdr {
    fn new() -> Self {
        Self(vec![0, 1, 0, 0])
    }

    fn pad(&mut self, align: usize) {
        while !(self.0.len() - 4).is_multiple_of(align) {
            self.0.push(0);
        }
    }

    fn u32(mut self, v: u32) -> Self {
        self.pad(4);
        self.0.extend(v.to_le_bytes());
        self
    }

    fn string(self, s: &str) -> Self {
        let mut c = self.u32(s.len() as u32 + 1);
        c.0.extend(s.as_bytes());
        c.0.push(0);
        c
    }

    fn f64s(mut self, values: &[f64]) -> Self {
        for v in values {
            self.pad(8);
            self.0.extend(v.to_le_bytes());
        }
        self
    }

    fn header(self, sec: i32, frame_id: &str) -> Self {
        self.u32(sec as u32).u32(0).string(frame_id)
    }
}

/// A `nav_msgs/Odometry` at `x` (identity orientation unless given), no covariance.
struct Odometry {
    sec: i32,
    frame_id: String,
    x: f64,
    orientation: [f64; 4],
}

fn odometry(sec: i32, x: f64) -> Odometry {
    Odometry {
        sec,
        frame_id: "odom".into(),
        x,
        orientation: [0.0, 0.0, 0.0, 1.0],
    }
}

impl Odometry {
    fn cdr(&self) -> Vec<u8> {
        let pose = [self.x, 0.0, 0.0];
        Cdr::new()
            .header(self.sec, &self.frame_id)
            .string("base_link")
            .f64s(&pose)
            .f64s(&self.orientation)
            .f64s(&[0.0; 36])
            .f64s(&[0.0; 6])
            .f64s(&[0.0; 36])
            .0
    }
}

/// A `geometry_msgs/PoseWithCovarianceStamped` at `x`, σ 0.1 on every axis.
fn prior(sec: i32, x: f64) -> Vec<u8> {
    let mut covariance = [0.0; 36];
    for i in 0..6 {
        covariance[i * 7] = 0.01;
    }
    Cdr::new()
        .header(sec, "map")
        .f64s(&[x, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
        .f64s(&covariance)
        .0
}

/// A server (with `extra` flags) and a `pose_graph_3d` session `name` bound to `/odom` and
/// `/gnss` on `domain`, its node in the ROS graph; the peer and the session's error stream.
async fn bound_session(
    extra: &[&str],
    name: &str,
    domain: u32,
) -> (
    TestServer,
    zenoh::Session,
    Subscriber<FifoChannelHandler<Sample>>,
) {
    let server = TestServer::start(extra);
    let session = json!({"session": name, "kind": "pose_graph_3d",
        "ros2": {"domain_id": domain, "odometry_topic": "/odom", "prior_topic": "/gnss",
                 "keyframe_distance": 1.0}});
    create(&client(), &server, &session).await;
    let z = zenoh_peer(&server.zenoh).await;
    let node = format!("factord_{name}");
    let joined = |nodes: &[(String, String)]| !holders(nodes, &node).is_empty();
    let nodes = ros_nodes_until(&z, domain, Duration::from_secs(10), joined).await;
    assert!(
        joined(&nodes),
        "the node is not in the ROS graph: {nodes:?}"
    );
    let errors = z
        .declare_subscriber(format!("factord/{name}/out/errors"))
        .await
        .expect("a subscriber");
    // An event is published only on keys the server knows a subscriber of, and zenoh tells it
    // of a new one a moment later: an error raised at once was lost (once in a loaded full
    // run). Declared after the errors' subscriber, the acks' one is heard after it (a
    // session's declarations travel in order): once an empty batch's ack arrives, both are.
    let acks = z
        .declare_subscriber(format!("factord/{name}/out/acks"))
        .await
        .expect("a subscriber");
    let batches = server.url(&format!("/v1/sessions/{name}/batches"));
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    loop {
        let (status, v) = post(&client(), &batches, &json!({"variables": []})).await;
        assert_eq!(status, 200, "{v}");
        if tokio::time::timeout(Duration::from_millis(200), acks.recv_async())
            .await
            .is_ok()
        {
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "the server never heard the subscriptions"
        );
    }
    (server, z, errors)
}

async fn put(z: &zenoh::Session, domain: u32, topic: &str, ros_type: &str, payload: Vec<u8>) {
    let key = format!("{domain}/{topic}/{ros_type}");
    z.put(key, payload)
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .expect("a put");
}

/// The next error event, within 10 s; asserts it is a `ros2_bad_message` on `field` whose
/// message contains `says`, and returns the message.
async fn refusal(
    errors: &Subscriber<FifoChannelHandler<Sample>>,
    field: &str,
    says: &str,
) -> String {
    let sample = tokio::time::timeout(Duration::from_secs(10), errors.recv_async())
        .await
        .unwrap_or_else(|_| panic!("no error event for `{says}` within 10 s"))
        .expect("the error stream");
    let event: Value = serde_json::from_slice(&sample.payload().to_bytes()).expect("JSON");
    let error = &event["error"];
    assert_eq!(error["code"], "ros2_bad_message", "{event}");
    assert_eq!(error["field"], field, "{event}");
    let message = error["message"].as_str().expect("a message").to_string();
    assert!(message.contains(says), "expected `{says}` in: {message}");
    println!("refused: {message}");
    message
}

/// The stamps of the session's variables, once it has `count` of them (within 10 s).
async fn stamps(server: &TestServer, name: &str, count: usize) -> Vec<f64> {
    let url = server.url(&format!("/v1/sessions/{name}/estimate"));
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    loop {
        let (status, v) = get(&client(), &url).await;
        assert_eq!(status, 200, "{v}");
        let variables = v["variables"].as_array().expect("variables");
        if variables.len() >= count || std::time::Instant::now() > deadline {
            return variables
                .iter()
                .map(|v| v["stamp"].as_f64().expect("a stamp"))
                .collect();
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// The server's peak resident set (VmHWM) after resetting it to the current one, in bytes.
fn reset_peak(server: &TestServer) -> u64 {
    std::fs::write(format!("/proc/{}/clear_refs", server.pid()), "5").expect("clear_refs");
    server.peak_rss()
}

/// Item 5: a ROS message beyond `max_body_bytes` is refused on its size, with an event and a
/// log line, and nothing of it is applied (here a well-formed odometry message whose frame id
/// makes it 100 kB, against a limit of 64 KiB).
#[tokio::test(flavor = "multi_thread")]
async fn a_ros_message_beyond_max_body_bytes_is_refused_unread() {
    let (domain, name) = (21, "ros_big");
    let (server, z, errors) = bound_session(&["--max-body-bytes", "65536"], name, domain).await;
    let mut big = odometry(1, 0.0);
    big.frame_id = "f".repeat(100_000);
    let payload = big.cdr();
    let len = payload.len();
    put(&z, domain, "odom", ODOMETRY, payload).await;
    let message = refusal(&errors, "ros2.odometry_topic", "max_body_bytes").await;
    assert!(
        message.contains(&format!("{len} bytes; the limit is 65536")),
        "{message}"
    );
    // The binding goes on: the next message is the first keyframe.
    put(&z, domain, "odom", ODOMETRY, odometry(2, 0.0).cdr()).await;
    assert_eq!(stamps(&server, name, 1).await, [2.0]);
    let log = server.stderr();
    assert!(
        log.contains("ROS message refused") && log.contains("max_body_bytes"),
        "no log line for the refusal:\n{log}"
    );
    server.assert_no_panic();
}

/// Item 11: stamps negative, repeated or going back, a position of 1e300, a zero quaternion, a
/// 10 MB frame id and a CDR string length of 0xFFFFFFF0 are each refused naming the field;
/// an absolute pose is held to the same bounds. Only the good messages make keyframes, in
/// time order, and the huge length costs no memory.
#[tokio::test(flavor = "multi_thread")]
async fn out_of_bounds_ros_values_are_refused_naming_the_field() {
    let (domain, name) = (22, "ros_bounds");
    let (server, z, errors) = bound_session(&[], name, domain).await;
    let odom = "ros2.odometry_topic";
    put(&z, domain, "odom", ODOMETRY, odometry(10, 0.0).cdr()).await;
    assert_eq!(stamps(&server, name, 1).await, [10.0]);

    // Every one of these has moved 5 m: it would be a keyframe if it were taken.
    let cases: Vec<(Odometry, &str)> = vec![
        (odometry(-5, 5.0), "header.stamp is -5.0 s"),
        (odometry(10, 5.0), "duplicate"),
        (odometry(9, 5.0), "out of order"),
        (odometry(11, 1e300), "pose.pose.position.x is 1e300"),
        (
            Odometry {
                orientation: [0.0; 4],
                ..odometry(11, 5.0)
            },
            "pose.pose.orientation has norm 0.0",
        ),
        (
            Odometry {
                frame_id: "f".repeat(10 << 20),
                ..odometry(11, 5.0)
            },
            "header.frame_id has a length of 10485761 bytes",
        ),
    ];
    for (message, says) in cases {
        put(&z, domain, "odom", ODOMETRY, message.cdr()).await;
        refusal(&errors, odom, says).await;
    }
    // A string length far beyond the payload: refused at the length, nothing allocated for it.
    let before = reset_peak(&server);
    let mut huge = Cdr::new().u32(11).u32(0).u32(0xFFFF_FFF0).0;
    huge.extend(b"odom\0");
    put(&z, domain, "odom", ODOMETRY, huge).await;
    refusal(
        &errors,
        odom,
        "header.frame_id has a length of 4294967280 bytes",
    )
    .await;
    let grown = server.peak_rss().saturating_sub(before);
    assert!(grown < 64 << 20, "the peak RSS grew {} MB", grown >> 20);

    // Absolute poses: the same value and stamp bounds.
    let gnss = "ros2.prior_topic";
    put(&z, domain, "gnss", PRIOR, prior(10, f64::NAN)).await;
    refusal(&errors, gnss, "pose.pose.position.x is NaN").await;
    put(&z, domain, "gnss", PRIOR, prior(-1, 0.0)).await;
    refusal(&errors, gnss, "header.stamp is -1.0 s").await;

    // The next good message is the second keyframe; nothing else was taken.
    put(&z, domain, "odom", ODOMETRY, odometry(12, 2.0).cdr()).await;
    assert_eq!(stamps(&server, name, 2).await, [10.0, 12.0]);
    server.assert_no_panic();
}
