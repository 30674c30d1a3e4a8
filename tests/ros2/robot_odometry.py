"""A ROS 2 robot as rmw_zenoh puts it on the wire, against a factord session bound to its topics.

No ROS installation: messages are written and read with rosbags' CDR serialiser (Jazzy type
store), samples carry rmw_zenoh's attachment (zenoh.ext serializer: sequence, timestamp, GID)
and the robot declares rmw_zenoh liveliness tokens, as rmw_zenoh_cpp would for a node with an
odometry publisher. Checks, in order:

1. factord's node and endpoints are in the ROS graph (liveliness tokens, exact format);
2. odometry becomes keyframes by the distance/angle thresholds, and the published nav_msgs/Path
   is those keyframes' odometry poses with their header stamps (the graph is consistent, so the
   optimum is odometry), with a well-formed attachment; the path is latched (transient local,
   depth 1): a subscriber that joins later, declared as rmw_zenoh declares a transient-local
   subscription, gets the last path from factord's publication cache at once;
3. a malformed payload and a message of the wrong type are reported on the session's error
   stream (`ros2_bad_message`) and change nothing: odometry keeps extending the path;
4. an absolute pose (PoseWithCovarianceStamped) pulls the trajectory to it, and the pose output
   carries a positive definite marginal covariance;
5. `/tf` carries the map → odom correction: identity while the optimum is odometry, then the
   pull; composed with the newest keyframe's odometry pose it is that keyframe's optimised pose;
   stamped at the newest odometry stamp plus the tolerance, strictly increasing.

Prints the key expressions, tokens and one captured attachment (hex).
"""

import argparse
import json
import math
import threading
import time
import urllib.request

import numpy as np
import xxhash
import zenoh
import zenoh.ext as zext
from rosbags.typesys import Stores, get_typestore

STORE = get_typestore(Stores.ROS2_JAZZY)
DOMAIN = 7
ODOM = "nav_msgs/msg/Odometry"
PWCS = "geometry_msgs/msg/PoseWithCovarianceStamped"
PATH = "nav_msgs/msg/Path"
TF = "tf2_msgs/msg/TFMessage"
TOLERANCE = 0.25


def dds_name(msgtype):
    pkg, kind, name = msgtype.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def topic_key(topic, msgtype):
    return f"{DOMAIN}/{topic.strip('/')}/{dds_name(msgtype)}/{STORE.hash_rihs01(msgtype)}"


def http(base, method, path, body=None):
    data = None if body is None else json.dumps(body).encode()
    request = urllib.request.Request(base + path, data=data, method=method,
                                     headers={"content-type": "application/json"})
    with urllib.request.urlopen(request, timeout=30) as response:
        return json.loads(response.read())


def wait_for(what, predicate, timeout=30.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def collector(received, lock):
    """Subscriber callbacks that append what they hear to `received[name]` under `lock`: ROS
    messages decoded (`messages(name, msgtype)`), or the session's errors (`errors()`, into
    `received["errors"]`)."""
    def messages(name, msgtype):
        def callback(sample):
            message = STORE.deserialize_cdr(bytes(sample.payload.to_bytes()), msgtype)
            with lock:
                received[name].append(message)
        return callback

    def errors():
        def callback(sample):
            with lock:
                received["errors"].append(json.loads(bytes(sample.payload.to_bytes())))
        return callback
    return messages, errors


class Robot:
    """A node `robot` with publishers (by default odometry and GNSS), as rmw_zenoh_cpp declares
    them."""

    def __init__(self, session, topics=(("/robot1/odom", ODOM), ("/robot1/gnss", PWCS))):
        self.session = session
        zid = str(session.zid())
        node = f"@ros2_lv/{DOMAIN}/{zid}/0/0/NN/%/%/robot"
        self.tokens = [session.liveliness().declare_token(node)]
        self.publishers = {}
        for eid, (topic, msgtype) in enumerate(topics, 1):
            token = (f"@ros2_lv/{DOMAIN}/{zid}/0/{eid}/MP/%/%/robot/{topic.replace('/', '%')}/"
                     f"{dds_name(msgtype)}/{STORE.hash_rihs01(msgtype)}/::,10:,:,:,,")
            self.tokens.append(session.liveliness().declare_token(token))
            gid = xxhash.xxh3_128(token.encode()).intdigest().to_bytes(16, "little")
            self.publishers[topic] = [topic_key(topic, msgtype), gid, 0]

    def publish(self, topic, payload):
        publisher = self.publishers[topic]
        publisher[2] += 1
        attachment = zext.z_serialize(
            (zext.Int64(publisher[2]), zext.Int64(time.time_ns()), publisher[1]))
        # Blocking, as rmw_zenoh publishes reliable topics that keep all: a test that floods
        # thousands of samples must not lose any on a busy machine.
        self.session.put(publisher[0], payload, attachment=attachment,
                         congestion_control=zenoh.CongestionControl.BLOCK)


def header(stamp, frame):
    Header = STORE.types["std_msgs/msg/Header"]
    Time = STORE.types["builtin_interfaces/msg/Time"]
    sec = int(math.floor(stamp))
    return Header(stamp=Time(sec=sec, nanosec=int(round((stamp - sec) * 1e9))), frame_id=frame)


def pose_msg(x, y, z, yaw):
    t = STORE.types
    return t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=x, y=y, z=z),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2),
                                                      w=math.cos(yaw / 2)))


def covariance(sigmas):
    return np.diag(np.square(np.array(sigmas, dtype=np.float64))).reshape(36)


def odometry(stamp, x, y, yaw, speed=1.0):
    """Odometry at (x, y, yaw), driving forward at `speed` (the twist is in the body frame)."""
    t = STORE.types
    twist = t["geometry_msgs/msg/TwistWithCovariance"](
        twist=t["geometry_msgs/msg/Twist"](
            linear=t["geometry_msgs/msg/Vector3"](x=speed, y=0.0, z=0.0),
            angular=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
        covariance=np.zeros(36))
    message = t[ODOM](
        header=header(stamp, "odom"), child_frame_id="base_link",
        pose=t["geometry_msgs/msg/PoseWithCovariance"](
            pose=pose_msg(x, y, 0.0, yaw), covariance=covariance([0.02] * 3 + [0.005] * 3)),
        twist=twist)
    return bytes(STORE.serialize_cdr(message, ODOM))


def trajectory():
    """A 20 Hz drive: straight, a left turn, straight again (stamp, x, y, yaw)."""
    samples, x, y, yaw, stamp = [], 0.0, 0.0, 0.0, 1_700_000_000.25
    for i in range(240):
        turning = 80 <= i < 140
        yaw += (math.pi / 2) / 60 if turning else 0.0
        x += 0.1 * math.cos(yaw)
        y += 0.1 * math.sin(yaw)
        stamp += 0.05
        samples.append((stamp, x, y, yaw))
    return samples


def keyframes(samples, distance, angle):
    """The messages factord should keep: as its keyframer, relative motion since the last."""
    kept = []
    for s in samples:
        if not kept:
            kept.append(s)
            continue
        _, kx, ky, kyaw = kept[-1]
        moved = math.hypot(s[1] - kx, s[2] - ky)
        turned = abs(math.atan2(math.sin(s[3] - kyaw), math.cos(s[3] - kyaw)))
        if moved >= distance or turned >= angle:
            kept.append(s)
    return kept


def zenoh_session(endpoint):
    """A zenoh peer connected to factord only (no scouting), as the robot's rmw_zenoh would be
    through its router."""
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("listen/endpoints", "[]")
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config)


def ros_graph(session):
    """Every liveliness token of the domain: the ROS graph as `ros2 node/topic list` sees it."""
    return [str(r.ok.key_expr) for r in session.liveliness().get(f"@ros2_lv/{DOMAIN}/**")
            if r.ok is not None]


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--http", required=True)
    parser.add_argument("--zenoh", required=True)
    args = parser.parse_args()

    binding = {
        "domain_id": DOMAIN, "odometry_topic": "/robot1/odom", "prior_topic": "/robot1/gnss",
        "path_topic": "/robot1/factord/path", "pose_topic": "/robot1/factord/pose",
        "tf_topic": "/tf", "transform_tolerance": TOLERANCE,
        "keyframe_distance": 1.0, "keyframe_angle": 0.5,
    }
    http(args.http, "POST", "/v1/sessions",
         {"session": "ros_robot", "kind": "pose_graph_3d", "ros2": binding})

    with zenoh_session(args.zenoh) as session:  # closed however run() ends
        run(session, args)


def run(session, args):
    # 1. The ROS graph: factord's node and its five endpoints.
    def graph():
        ours = [t for t in ros_graph(session) if "/factord_ros_robot" in t]
        return ours if len(ours) == 6 else None
    tokens = sorted(wait_for("factord's liveliness tokens", graph), key=lambda t: t.split("/")[5])
    for token in tokens:
        print("liveliness:", token)
    kinds = sorted(t.split("/")[5] for t in tokens)
    assert kinds == ["MP", "MP", "MP", "MS", "MS", "NN"], kinds
    expected_tails = {
        f"%robot1%odom/{dds_name(ODOM)}/{STORE.hash_rihs01(ODOM)}/::,10:,:,:,,",
        f"%robot1%gnss/{dds_name(PWCS)}/{STORE.hash_rihs01(PWCS)}/::,10:,:,:,,",
        f"%robot1%factord%path/{dds_name(PATH)}/{STORE.hash_rihs01(PATH)}/:1:,1:,:,:,,",
        f"%robot1%factord%pose/{dds_name(PWCS)}/{STORE.hash_rihs01(PWCS)}/::,10:,:,:,,",
        f"%tf/{dds_name(TF)}/{STORE.hash_rihs01(TF)}/::,10:,:,:,,",
    }
    for token in tokens:
        parts = token.split("/")
        assert parts[:2] == ["@ros2_lv", str(DOMAIN)] and parts[6:9] == ["%", "%", "factord_ros_robot"], token
    assert {"/".join(t.split("/")[9:]) for t in tokens if "/NN/" not in t} == expected_tails

    # Outputs, read as a ROS subscriber would (CDR and attachment decoded).
    received = {"path": [], "pose": [], "tf": [], "errors": []}
    lock = threading.Lock()

    def on(kind, msgtype):
        def callback(sample):
            try:
                take(sample)
            except Exception as e:  # a callback's exception would be lost in zenoh's thread
                with lock:
                    received["errors"].append({"error": {"code": "callback", "message": repr(e)}})

        def take(sample):
            message = STORE.deserialize_cdr(bytes(sample.payload.to_bytes()), msgtype)
            attachment = bytes(sample.attachment.to_bytes())
            seq, stamp, gid = zext.z_deserialize(tuple[zext.Int64, zext.Int64, bytes],
                                                 sample.attachment)
            with lock:
                received[kind].append((message, attachment, int(seq), int(stamp), gid))
        return callback

    def on_error(sample):
        with lock:
            received["errors"].append(json.loads(bytes(sample.payload.to_bytes())))
    path_key = topic_key("/robot1/factord/path", PATH)
    pose_key = topic_key("/robot1/factord/pose", PWCS)
    tf_key = topic_key("/tf", TF)
    print("odometry key:", topic_key("/robot1/odom", ODOM))
    print("gnss key:", topic_key("/robot1/gnss", PWCS))
    print("path key:", path_key)
    print("pose key:", pose_key)
    print("tf key:", tf_key)
    subscribers = [session.declare_subscriber(path_key, on("path", PATH)),
                   session.declare_subscriber(pose_key, on("pose", PWCS)),
                   session.declare_subscriber(tf_key, on("tf", TF)),
                   session.declare_subscriber("factord/ros_robot/out/errors", on_error)]
    robot = Robot(session)
    time.sleep(0.5)  # let factord's subscriptions see our publishers' routes

    # 2. Odometry in, the optimised path out.
    samples = trajectory()
    first, rest = samples[:200], samples[200:]
    for s in first:
        robot.publish("/robot1/odom", odometry(*s))
        time.sleep(0.002)
    expected = keyframes(first, 1.0, 0.5)

    def latest_path(count):
        def check():
            with lock:
                if received["path"] and len(received["path"][-1][0].poses) == count:
                    return received["path"][-1]
            return None
        return check
    try:
        message, attachment, seq, stamp, gid = wait_for(
            f"a path of {len(expected)} keyframes", latest_path(len(expected)))
    except AssertionError:
        with lock:
            print("paths received:", [len(p[0].poses) for p in received["path"]])
            print("errors:", received["errors"])
        print("session:", http(args.http, "GET", "/v1/sessions/ros_robot"))
        raise
    assert len(attachment) == 33 and attachment[16] == 16, attachment.hex()
    assert seq >= 1 and abs(stamp - time.time_ns()) < 60e9, (seq, stamp)
    path_token = next(t for t in tokens if "%factord%path" in t)
    assert gid == xxhash.xxh3_128(path_token.encode()).intdigest().to_bytes(16, "little"), \
        "the GID is XXH3-128 of the publisher's liveliness token"
    print(f"captured attachment (path, sequence {seq}): {attachment.hex()}")
    assert message.header.frame_id == "map"
    worst = 0.0
    for got, (s_stamp, x, y, yaw) in zip(message.poses, expected):
        got_stamp = got.header.stamp.sec + got.header.stamp.nanosec * 1e-9
        assert abs(got_stamp - s_stamp) < 1e-6, (got_stamp, s_stamp)
        p, q = got.pose.position, got.pose.orientation
        got_yaw = 2 * math.atan2(q.z, q.w)
        err = max(abs(p.x - x), abs(p.y - y), abs(p.z),
                  abs(math.atan2(math.sin(got_yaw - yaw), math.cos(got_yaw - yaw))))
        worst = max(worst, err)
    assert worst < 1e-6, f"optimised path differs from the odometry by {worst}"
    print(f"path: {len(message.poses)} keyframes of {len(first)} odometry messages, "
          f"max deviation from odometry {worst:.2e}")
    check_late_joiner(args.zenoh, path_key, received, lock)

    # 3. Bad input is reported, never applied.
    robot.publish("/robot1/odom", b"\x00\x01\x00\x00garbage")
    prior_on_odom = STORE.types[PWCS](header=header(1.0, "map"), pose=STORE.types[
        "geometry_msgs/msg/PoseWithCovariance"](pose=pose_msg(0, 0, 0, 0), covariance=np.zeros(36)))
    robot.publish("/robot1/odom", bytes(STORE.serialize_cdr(prior_on_odom, PWCS)))
    errors = wait_for("two ros2_bad_message errors", lambda: (
        [e for e in received["errors"] if e["error"]["code"] == "ros2_bad_message"]
        if len([e for e in received["errors"] if e["error"]["code"] == "ros2_bad_message"]) >= 2
        else None))
    for e in errors:
        print("error event:", e["error"]["message"])
    for s in rest:
        robot.publish("/robot1/odom", odometry(*s))
        time.sleep(0.002)
    expected = keyframes(samples, 1.0, 0.5)
    message = wait_for(f"a path of {len(expected)} keyframes after the bad input",
                       latest_path(len(expected)))[0]
    last = message.poses[-1].pose.position
    assert abs(last.x - expected[-1][1]) < 1e-6 and abs(last.y - expected[-1][2]) < 1e-6

    # 4. An absolute pose 0.5 m off the last keyframe pulls the trajectory there.
    s_stamp, x, y, yaw = expected[-1]
    gnss = STORE.types[PWCS](header=header(s_stamp + 0.01, "map"), pose=STORE.types[
        "geometry_msgs/msg/PoseWithCovariance"](pose=pose_msg(x + 0.5, y, 0.0, yaw),
                                                covariance=covariance([0.01] * 3 + [0.01] * 3)))
    robot.publish("/robot1/gnss", bytes(STORE.serialize_cdr(gnss, PWCS)))

    def pulled():
        with lock:
            if received["pose"]:
                message = received["pose"][-1][0]
                if abs(message.pose.pose.position.x - (x + 0.5)) < 0.01:
                    return message
        return None
    pose = wait_for("the pose pulled to the absolute pose", pulled)
    cov = np.array(pose.pose.covariance).reshape(6, 6)
    assert np.all(np.linalg.eigvalsh((cov + cov.T) / 2) > 0), cov
    assert cov[0, 0] < 0.01 ** 2 * 1.01, cov[0, 0]
    print(f"pose after the prior: x {pose.pose.pose.position.x:.4f} (prior {x + 0.5:.4f}), "
          f"sigma_x {math.sqrt(cov[0, 0]):.4f} m")
    check_tf(received, lock, robot, expected[-1], samples[-1][0])
    for subscriber in subscribers:
        subscriber.undeclare()
    print("ros2 robot: ok")


def check_late_joiner(endpoint, path_key, received, lock):
    """A subscriber that joins after the path was published, in a session of its own (an
    operator's RViz started later), declared as rmw_zenoh declares a transient-local, reliable,
    depth-1 subscription: an advanced subscriber that queries late publishers' caches. It must
    get the last path at once, without a new publication: the very sample (same attachment
    sequence) the robot's subscriber got before the late one was declared."""
    with lock:
        published = {seq for _, _, seq, _, _ in received["path"]}
        newest = received["path"][-1][0]
    late = []
    with zenoh_session(endpoint) as session:
        subscriber = zext.declare_advanced_subscriber(
            session, path_key,
            lambda sample: late.append((STORE.deserialize_cdr(
                bytes(sample.payload.to_bytes()), PATH), zext.z_deserialize(
                    tuple[zext.Int64, zext.Int64, bytes], sample.attachment)[0])),
            history=zext.HistoryConfig(detect_late_publishers=True, max_samples=1),
            recovery=zext.RecoveryConfig(periodic_queries=None, heartbeat=True),
            subscriber_detection=True)
        message, seq = wait_for("the latched path at a late subscriber",
                                lambda: late[0] if late else None, timeout=10.0)
        subscriber.undeclare()
    assert int(seq) in published, f"sequence {seq} was not published before ({sorted(published)})"
    assert len(message.poses) == len(newest.poses), (len(message.poses), len(newest.poses))
    print(f"late subscriber: the latched path (sequence {seq}, {len(message.poses)} keyframes) "
          "from factord's cache")


def pose_matrix(translation, rotation):
    """A 4×4 transform from a position and a quaternion message."""
    x, y, z, w = rotation.x, rotation.y, rotation.z, rotation.w
    matrix = np.eye(4)
    matrix[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    matrix[:3, 3] = [translation.x, translation.y, translation.z]
    return matrix


def stamp_of(header):
    return header.stamp.sec + header.stamp.nanosec * 1e-9


def check_tf(received, lock, robot, last_keyframe, newest_odometry):
    """5. map → odom on /tf (see the module's doc)."""
    with lock:
        transforms = [m[0].transforms for m in received["tf"]]
    assert transforms and all(len(t) == 1 for t in transforms), transforms[:3]
    first = transforms[0][0]
    assert (first.header.frame_id, first.child_frame_id) == ("map", "odom"), first
    identity = pose_matrix(first.transform.translation, first.transform.rotation)
    assert np.abs(identity - np.eye(4)).max() < 1e-6, identity

    # The pulled correction: the newest keyframe's odometry pose carried to its optimum.
    stamp, x, y, yaw = last_keyframe
    odometry_pose = pose_matrix(STORE.types["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
                                pose_msg(x, y, 0.0, yaw).orientation)

    def pulled():
        with lock:
            if received["tf"]:
                t = received["tf"][-1][0].transforms[0].transform
                if abs(t.translation.x - 0.5) < 0.02:
                    return received["tf"][-1][0].transforms[0], received["path"][-1][0]
        return None
    correction, path = wait_for("the map -> odom correction after the pull", pulled)
    time.sleep(0.3)  # the path and the correction of the last solve
    with lock:
        correction, path = received["tf"][-1][0].transforms[0], received["path"][-1][0]
    optimised = path.poses[-1].pose
    composed = pose_matrix(correction.transform.translation, correction.transform.rotation) \
        @ odometry_pose
    wanted = pose_matrix(optimised.position, optimised.orientation)
    assert np.abs(composed - wanted).max() < 1e-6, (composed, wanted)
    print(f"map -> odom after the pull: t = ({correction.transform.translation.x:.4f}, "
          f"{correction.transform.translation.y:.4f}, {correction.transform.translation.z:.4f})")

    # Odometry that makes no keyframe (the robot stands at its last keyframe) re-dates it.
    for i in range(1, 4):
        robot.publish("/robot1/odom", odometry(newest_odometry + 0.1 * i, x, y, yaw))
        time.sleep(0.05)
    newest = newest_odometry + 0.3 + TOLERANCE

    def redated():
        with lock:
            if received["tf"] and abs(stamp_of(received["tf"][-1][0].transforms[0].header)
                                      - newest) < 1e-6:
                return received["tf"][-1][0].transforms[0]
        return None
    wait_for("the correction dated at the newest odometry stamp plus the tolerance", redated)
    with lock:
        stamps = [m[0].transforms[0].header.stamp for m in received["tf"]]
    # In nanoseconds, as tf2 keeps them (a float of epoch seconds cannot tell 1 ns apart).
    stamps = [s.sec * 10**9 + s.nanosec for s in stamps]
    assert all(b > a for a, b in zip(stamps, stamps[1:])), stamps
    print(f"tf: {len(stamps)} map -> odom transforms, stamps strictly increasing")


if __name__ == "__main__":
    main()
